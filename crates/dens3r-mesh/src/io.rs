//! Mesh files: read PLY (ASCII / binary), OBJ (through tobj) and OFF; write binary PLY and
//! OBJ. Writes are atomic: a temporary file in the target folder, renamed when complete.

use crate::TriMesh;
use dens3r_io::write_atomic;
use glam::Vec3;
use std::fs::File;
use std::io::{BufReader, Read, Write};
use std::path::Path;

dens3r_io::file_error! {
    /// A mesh file could not be read or written; the message names the file and the fix.
    MeshError;
    from: [dens3r_io::IoError];
}

/// Reads a triangle mesh by extension (`.ply`, `.obj`, `.off`, `.glb`). Polygons are fan-triangulated.
pub fn read_mesh(path: &Path) -> Result<TriMesh, MeshError> {
    if !path.is_file() {
        return Err(MeshError::new(path, "mesh file not found (check the path)"));
    }
    let ext = extension(path);
    let mesh = match ext.as_str() {
        "ply" => read_ply(path)?,
        "obj" => read_obj(path)?,
        "off" => read_off(path)?,
        "glb" | "gltf" => {
            let bytes = std::fs::read(path).map_err(|e| MeshError::new(path, format!("cannot read: {e}")))?;
            crate::glb::from_glb(&bytes).map_err(|m| MeshError::new(path, m.0))?
        }
        _ => return Err(MeshError::new(path, "unknown mesh format: use .ply, .obj or .off")),
    };
    mesh.validate().map_err(|m| MeshError::new(path, format!("invalid mesh: {m}")))?;
    if mesh.indices.is_empty() {
        return Err(MeshError::new(path, "mesh has no triangles (a point cloud is not a mesh)"));
    }
    Ok(mesh)
}

/// Writes a mesh by extension (`.ply` binary little-endian, `.obj`, `.glb`), atomically.
pub fn write_mesh(path: &Path, mesh: &TriMesh) -> Result<(), MeshError> {
    mesh.validate().map_err(|m| MeshError::new(path, format!("refusing to write an invalid mesh: {m}")))?;
    match extension(path).as_str() {
        "ply" => Ok(write_atomic(path, |w| write_ply(w, mesh))?),
        "obj" => Ok(write_atomic(path, |w| write_obj(w, mesh))?),
        "glb" => {
            let bytes = crate::glb::to_glb(mesh).map_err(|m| MeshError::new(path, m.0))?;
            Ok(write_atomic(path, |w| w.write_all(&bytes))?)
        }
        _ => Err(MeshError::new(path, "unknown output mesh format: use .ply, .obj or .glb")),
    }
}

fn extension(path: &Path) -> String {
    path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase()
}

fn fan(face: &[u32], out: &mut Vec<[u32; 3]>) {
    for k in 1..face.len().saturating_sub(1) {
        out.push([face[0], face[k], face[k + 1]]);
    }
}

/// Checks a PLY header's element counts against the file size before the parser allocates
/// for them: each element takes at least one byte per property in binary files and two
/// (a digit and a separator) in ASCII ones.
fn check_ply_counts(path: &Path) -> Result<(), MeshError> {
    let bad = |m: String| MeshError::new(path, format!("not a valid PLY file: {m}"));
    let file = File::open(path).map_err(|e| MeshError::new(path, format!("cannot open: {e}")))?;
    let len = file.metadata().map_err(|e| MeshError::new(path, format!("cannot open: {e}")))?.len();
    let mut header = Vec::new();
    std::io::Read::take(file, 1 << 20)
        .read_to_end(&mut header)
        .map_err(|e| MeshError::new(path, format!("cannot read: {e}")))?;
    let text = String::from_utf8_lossy(&header);
    let Some(end) = text.find("end_header") else { return Ok(()) }; // the parser reports it
    let ascii = text[..end].contains("format ascii");
    let (mut need, mut count, mut props) = (0u64, 0u64, 0u64);
    for line in text[..end].lines() {
        let t: Vec<&str> = line.split_whitespace().collect();
        match t.as_slice() {
            ["element", _, n] => {
                need = need.saturating_add(count.saturating_mul(props.max(1)));
                count = n.parse().map_err(|_| bad(format!("element count '{n}' is not a number")))?;
                props = 0;
            }
            ["property", ..] => props += 1,
            _ => {}
        }
    }
    need = need.saturating_add(count.saturating_mul(props.max(1)));
    let need = if ascii { need.saturating_mul(2) } else { need };
    if need > len {
        return Err(bad(format!(
            "its header declares elements needing at least {need} bytes but the file holds {len} (a damaged or hostile header)"
        )));
    }
    Ok(())
}

fn read_ply(path: &Path) -> Result<TriMesh, MeshError> {
    use ply_rs_bw::parser::Parser;
    use ply_rs_bw::ply::{DefaultElement, Property};
    check_ply_counts(path)?;
    let mut f = BufReader::new(File::open(path).map_err(|e| MeshError::new(path, format!("cannot open: {e}")))?);
    let ply = Parser::<DefaultElement>::new()
        .read_ply(&mut f)
        .map_err(|e| MeshError::new(path, format!("not a readable PLY file ({e}); re-export it as PLY")))?;
    let verts = ply.payload.get("vertex").ok_or_else(|| MeshError::new(path, "PLY has no 'vertex' element"))?;
    let scalar = |e: &DefaultElement, k: &str| e.get(k).and_then(Property::to_f32_lossy);
    let mut positions = Vec::with_capacity(verts.len());
    for (i, v) in verts.iter().enumerate() {
        match (scalar(v, "x"), scalar(v, "y"), scalar(v, "z")) {
            (Some(x), Some(y), Some(z)) => positions.push(Vec3::new(x, y, z)),
            _ => return Err(MeshError::new(path, format!("vertex {i} lacks numeric x, y, z"))),
        }
    }
    let normals = verts
        .iter()
        .map(|v| Some(Vec3::new(scalar(v, "nx")?, scalar(v, "ny")?, scalar(v, "nz")?)))
        .collect::<Option<Vec<_>>>()
        .filter(|n| !n.is_empty());
    let colors = verts
        .iter()
        .map(|v| {
            let c = |k: &str| v.get(k).and_then(Property::to_u8_color_lossy);
            Some([c("red")?, c("green")?, c("blue")?])
        })
        .collect::<Option<Vec<_>>>()
        .filter(|c| !c.is_empty());
    let mut indices = Vec::new();
    for (i, face) in ply.payload.get("face").map(Vec::as_slice).unwrap_or(&[]).iter().enumerate() {
        let list = face.get("vertex_indices").or_else(|| face.get("vertex_index"));
        let idx: Vec<u32> = match list {
            Some(Property::ListInt(v)) => v.iter().map(|&x| x as u32).collect(),
            Some(Property::ListUInt(v)) => v.clone(),
            Some(Property::ListUChar(v)) => v.iter().map(|&x| x as u32).collect(),
            Some(Property::ListChar(v)) => v.iter().map(|&x| x as u32).collect(),
            Some(Property::ListShort(v)) => v.iter().map(|&x| x as u32).collect(),
            Some(Property::ListUShort(v)) => v.iter().map(|&x| x as u32).collect(),
            _ => return Err(MeshError::new(path, format!("face {i} has no integer 'vertex_indices' list"))),
        };
        fan(&idx, &mut indices);
    }
    Ok(TriMesh { positions, indices, normals, colors })
}

fn read_obj(path: &Path) -> Result<TriMesh, MeshError> {
    let opts = tobj::LoadOptions { triangulate: true, single_index: true, ..Default::default() };
    let (models, _) =
        tobj::load_obj(path, &opts).map_err(|e| MeshError::new(path, format!("not a readable OBJ file: {e}")))?;
    let mut out = TriMesh::default();
    for (k, m) in models.iter().enumerate() {
        let m = &m.mesh;
        let chunk = |v: &[f32]| v.chunks_exact(3).map(|c| Vec3::new(c[0], c[1], c[2])).collect::<Vec<_>>();
        let positions = chunk(&m.positions);
        let n = positions.len();
        let mut part = TriMesh::new(positions, m.indices.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect());
        if m.normals.len() == 3 * n && n > 0 {
            part.normals = Some(chunk(&m.normals));
        }
        if m.vertex_color.len() == 3 * n && n > 0 {
            let to_u8 = |x: f32| (x.clamp(0.0, 1.0) * 255.0).round() as u8;
            part.colors =
                Some(m.vertex_color.chunks_exact(3).map(|c| [to_u8(c[0]), to_u8(c[1]), to_u8(c[2])]).collect());
        }
        if k == 0 {
            out = part;
        } else {
            out.append(&part);
        }
    }
    Ok(out)
}

fn read_off(path: &Path) -> Result<TriMesh, MeshError> {
    let mut text = String::new();
    File::open(path)
        .and_then(|mut f| f.read_to_string(&mut text))
        .map_err(|e| MeshError::new(path, format!("cannot read as text: {e}")))?;
    let mut lines = text.lines().map(|l| l.split('#').next().unwrap_or("").trim()).filter(|l| !l.is_empty());
    let bad = |m: &str| MeshError::new(path, format!("not a valid OFF file: {m}"));
    let header = lines.next().ok_or_else(|| bad("empty file"))?;
    let mut toks: Vec<&str> = header.split_whitespace().collect();
    if !toks[0].ends_with("OFF") {
        return Err(bad("first line must be OFF (or COFF / NOFF)"));
    }
    toks.remove(0);
    if toks.is_empty() {
        toks = lines.next().ok_or_else(|| bad("missing counts line"))?.split_whitespace().collect();
    }
    let count = |i: usize| {
        toks.get(i)
            .and_then(|t| t.parse::<usize>().ok())
            .ok_or_else(|| bad("counts line must hold vertex and face counts"))
    };
    let (nv, nf) = (count(0)?, count(1)?);
    // Every vertex line takes at least 6 bytes ("0 0 0\n"), every face line 8 ("3 0 1 2\n"):
    // the capacities are bounded by what the file can hold, so a hostile header cannot make
    // us allocate more than the file's size (its shortfall is then reported line by line).
    let (cap_v, cap_f) = (nv.min(text.len() / 6), nf.min(text.len() / 8));
    let mut positions = Vec::with_capacity(cap_v);
    for i in 0..nv {
        let l = lines.next().ok_or_else(|| bad(&format!("file ends at vertex {i} of {nv}")))?;
        let v: Vec<f32> = l
            .split_whitespace()
            .take(3)
            .map(str::parse)
            .collect::<Result<_, _>>()
            .map_err(|_| bad(&format!("vertex {i} is not numeric")))?;
        if v.len() < 3 {
            return Err(bad(&format!("vertex {i} has fewer than 3 coordinates")));
        }
        positions.push(Vec3::new(v[0], v[1], v[2]));
    }
    let mut indices = Vec::with_capacity(cap_f);
    for i in 0..nf {
        let l = lines.next().ok_or_else(|| bad(&format!("file ends at face {i} of {nf}")))?;
        let mut it = l.split_whitespace().map(str::parse::<u32>);
        let k = it.next().and_then(Result::ok).ok_or_else(|| bad(&format!("face {i} has no vertex count")))? as usize;
        let face: Vec<u32> =
            it.take(k).collect::<Result<_, _>>().map_err(|_| bad(&format!("face {i} has a non-integer index")))?;
        if face.len() != k {
            return Err(bad(&format!("face {i} lists fewer than {k} vertices")));
        }
        fan(&face, &mut indices);
    }
    Ok(TriMesh::new(positions, indices))
}

fn write_ply(w: &mut impl Write, m: &TriMesh) -> std::io::Result<()> {
    writeln!(w, "ply\nformat binary_little_endian 1.0\ncomment written by dens3r")?;
    writeln!(w, "element vertex {}\nproperty float x\nproperty float y\nproperty float z", m.positions.len())?;
    if m.normals.is_some() {
        writeln!(w, "property float nx\nproperty float ny\nproperty float nz")?;
    }
    if m.colors.is_some() {
        writeln!(w, "property uchar red\nproperty uchar green\nproperty uchar blue")?;
    }
    writeln!(w, "element face {}\nproperty list uchar int vertex_indices\nend_header", m.indices.len())?;
    for (i, p) in m.positions.iter().enumerate() {
        for c in p.to_array() {
            w.write_all(&c.to_le_bytes())?;
        }
        if let Some(n) = &m.normals {
            for c in n[i].to_array() {
                w.write_all(&c.to_le_bytes())?;
            }
        }
        if let Some(c) = &m.colors {
            w.write_all(&c[i])?;
        }
    }
    for f in &m.indices {
        w.write_all(&[3])?;
        for i in f {
            w.write_all(&(*i as i32).to_le_bytes())?;
        }
    }
    Ok(())
}

fn write_obj(w: &mut impl Write, m: &TriMesh) -> std::io::Result<()> {
    writeln!(w, "# written by dens3r")?;
    for (i, p) in m.positions.iter().enumerate() {
        match &m.colors {
            Some(c) => {
                let c = c[i].map(|x| x as f32 / 255.0);
                writeln!(w, "v {} {} {} {} {} {}", p.x, p.y, p.z, c[0], c[1], c[2])?
            }
            None => writeln!(w, "v {} {} {}", p.x, p.y, p.z)?,
        }
    }
    if let Some(ns) = &m.normals {
        for n in ns {
            writeln!(w, "vn {} {} {}", n.x, n.y, n.z)?;
        }
    }
    for f in &m.indices {
        let [a, b, c] = f.map(|i| i + 1);
        if m.normals.is_some() {
            writeln!(w, "f {a}//{a} {b}//{b} {c}//{c}")?;
        } else {
            writeln!(w, "f {a} {b} {c}")?;
        }
    }
    Ok(())
}
