//! Binary glTF 2.0 (`.glb`) for triangle meshes: one mesh, one primitive with POSITION,
//! NORMAL, COLOR_0 (normalised u8, alpha 255) and u32 indices. The container is written and
//! read with the `gltf` crate. Coordinates are written as they are (glTF viewers assume +Y up;
//! our rendered scenes are +Z up, Dens3R camera frames +Y down).

use crate::{InvalidMesh, TriMesh};
use glam::Vec3;
use serde_json::json;
use std::borrow::Cow;

/// Serialises a mesh as GLB bytes.
pub fn to_glb(m: &TriMesh) -> Result<Vec<u8>, InvalidMesh> {
    write_glb(m).map_err(InvalidMesh)
}

fn write_glb(m: &TriMesh) -> Result<Vec<u8>, String> {
    let n = m.positions.len();
    let mut bin: Vec<u8> = Vec::new();
    let mut views = Vec::new();
    let mut accessors = Vec::new();
    let mut attributes = serde_json::Map::new();
    let push_view = |bin: &mut Vec<u8>, views: &mut Vec<serde_json::Value>, bytes: &[u8], target: u32| {
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        views.push(json!({"buffer": 0, "byteOffset": bin.len(), "byteLength": bytes.len(), "target": target}));
        bin.extend_from_slice(bytes);
        views.len() - 1
    };
    let (lo, hi) = m.bounds().ok_or("mesh has no vertices")?;
    let pos: Vec<u8> = m.positions.iter().flat_map(|p| p.to_array()).flat_map(f32::to_le_bytes).collect();
    let v = push_view(&mut bin, &mut views, &pos, 34962);
    accessors.push(json!({"bufferView": v, "componentType": 5126, "count": n, "type": "VEC3",
        "min": lo.to_array(), "max": hi.to_array()}));
    attributes.insert("POSITION".into(), json!(accessors.len() - 1));
    if let Some(ns) = &m.normals {
        let b: Vec<u8> =
            ns.iter().map(|v| v.normalize_or(Vec3::Z)).flat_map(|v| v.to_array()).flat_map(f32::to_le_bytes).collect();
        let v = push_view(&mut bin, &mut views, &b, 34962);
        accessors.push(json!({"bufferView": v, "componentType": 5126, "count": n, "type": "VEC3"}));
        attributes.insert("NORMAL".into(), json!(accessors.len() - 1));
    }
    if let Some(cs) = &m.colors {
        let b: Vec<u8> = cs.iter().flat_map(|c| [c[0], c[1], c[2], 255]).collect();
        let v = push_view(&mut bin, &mut views, &b, 34962);
        accessors.push(json!({"bufferView": v, "componentType": 5121, "normalized": true, "count": n, "type": "VEC4"}));
        attributes.insert("COLOR_0".into(), json!(accessors.len() - 1));
    }
    let idx: Vec<u8> = m.indices.iter().flatten().flat_map(|i| i.to_le_bytes()).collect();
    let v = push_view(&mut bin, &mut views, &idx, 34963);
    accessors.push(json!({"bufferView": v, "componentType": 5125, "count": 3 * m.indices.len(), "type": "SCALAR"}));
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let doc = json!({
        "asset": {"version": "2.0", "generator": "dens3r"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": attributes, "indices": accessors.len() - 1, "mode": 4}]}],
        "buffers": [{"byteLength": bin.len()}],
        "bufferViews": views,
        "accessors": accessors,
    });
    let mut json_bytes = serde_json::to_vec(&doc).map_err(|e| e.to_string())?;
    while !json_bytes.len().is_multiple_of(4) {
        json_bytes.push(b' ');
    }
    let glb = gltf::binary::Glb {
        header: gltf::binary::Header { magic: *b"glTF", version: 2, length: 0 },
        json: Cow::Owned(json_bytes),
        bin: Some(Cow::Owned(bin)),
    };
    glb.to_vec().map_err(|e| e.to_string())
}

/// Reads the triangles of every primitive of every mesh of a GLB / glTF-with-embedded-buffer
/// file (node transforms are not applied).
pub fn from_glb(bytes: &[u8]) -> Result<TriMesh, InvalidMesh> {
    // The gltf crate (1.4) panics on some damaged files (an accessor index past the list, a
    // GLB length under its header's, an out-of-range component type): such a panic is a
    // refusal of the file, not a crash.
    dens3r_io::panics::catch_quietly(|| read_glb(bytes))
        .unwrap_or_else(|e| Err(format!("the file is damaged (the glTF reader failed: {e})")))
        .map_err(InvalidMesh)
}

fn read_glb(bytes: &[u8]) -> Result<TriMesh, String> {
    let g = gltf::Gltf::from_slice(bytes).map_err(|e| format!("not a readable glTF file ({e})"))?;
    let blob = g.blob.as_deref();
    let mut out = TriMesh::new(Vec::new(), Vec::new());
    let (mut normals, mut colors) = (Vec::new(), Vec::new());
    let (mut all_normals, mut all_colors) = (true, true);
    for mesh in g.meshes() {
        for prim in mesh.primitives() {
            if prim.mode() != gltf::mesh::Mode::Triangles {
                continue;
            }
            let reader = prim.reader(|b| match b.source() {
                gltf::buffer::Source::Bin => blob,
                gltf::buffer::Source::Uri(_) => None,
            });
            let base = out.positions.len() as u32;
            let pos: Vec<Vec3> = reader.read_positions().ok_or("primitive without POSITION")?.map(Vec3::from).collect();
            let count = pos.len();
            out.positions.extend(pos);
            match reader.read_normals() {
                Some(ns) => normals.extend(ns.map(Vec3::from)),
                None => all_normals = false,
            }
            match reader.read_colors(0) {
                Some(cs) => colors.extend(cs.into_rgb_u8()),
                None => all_colors = false,
            }
            let idx: Vec<u32> = match reader.read_indices() {
                Some(i) => i.into_u32().collect(),
                None => (0..count as u32).collect(),
            };
            if idx.iter().any(|&i| i as usize >= count) {
                return Err("an index points past the vertices".into());
            }
            out.indices.extend(idx.chunks_exact(3).map(|t| [t[0] + base, t[1] + base, t[2] + base]));
        }
    }
    if out.indices.is_empty() {
        return Err("no triangles in the file".into());
    }
    if all_normals && normals.len() == out.positions.len() {
        out.normals = Some(normals);
    }
    if all_colors && colors.len() == out.positions.len() {
        out.colors = Some(colors);
    }
    Ok(out)
}
