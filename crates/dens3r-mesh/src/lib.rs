//! Triangle meshes for dens3r: the [`TriMesh`] type, PLY / OBJ / OFF I/O ([`io`]), primitive
//! shapes ([`primitives`]), area-weighted surface sampling ([`sample`]) and mesh-to-mesh
//! metrics ([`metrics`]: Chamfer-L1, F-score, normal consistency).

pub mod glb;
pub mod io;
pub mod metrics;
pub mod primitives;
pub mod sample;

use glam::Vec3;

pub use io::{read_mesh, write_mesh, MeshError};
pub use metrics::{mesh_metrics, mesh_metrics_where, MeshMetrics, MeshMetricsOptions};

/// A mesh that cannot be used as it is (an index past the vertices, a non-finite position,
/// nothing to sample), or a request it cannot answer; one line saying what.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct InvalidMesh(pub String);

impl From<&str> for InvalidMesh {
    fn from(m: &str) -> Self {
        Self(m.into())
    }
}

impl From<String> for InvalidMesh {
    fn from(m: String) -> Self {
        Self(m)
    }
}

/// An indexed triangle mesh with optional per-vertex normals and colours.
/// Triangles are counter-clockwise seen from outside (the normal side).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TriMesh {
    /// Vertex positions.
    pub positions: Vec<Vec3>,
    /// Triangles as vertex indices.
    pub indices: Vec<[u32; 3]>,
    /// Optional per-vertex unit normals (same length as `positions`).
    pub normals: Option<Vec<Vec3>>,
    /// Optional per-vertex sRGB colours (same length as `positions`).
    pub colors: Option<Vec<[u8; 3]>>,
}

impl TriMesh {
    /// A mesh from positions and triangles.
    pub fn new(positions: Vec<Vec3>, indices: Vec<[u32; 3]>) -> Self {
        Self { positions, indices, normals: None, colors: None }
    }

    /// Checks indices are in range, positions finite and attribute lengths consistent.
    pub fn validate(&self) -> Result<(), InvalidMesh> {
        let n = self.positions.len();
        if let Some(i) = self.positions.iter().position(|p| !p.is_finite()) {
            return Err(format!("vertex {i} is not finite").into());
        }
        if let Some((t, _)) = self.indices.iter().enumerate().find(|(_, f)| f.iter().any(|&v| v as usize >= n)) {
            return Err(format!("triangle {t} refers to a vertex past the {n} vertices").into());
        }
        if self.normals.as_ref().is_some_and(|v| v.len() != n) {
            return Err("normal count differs from vertex count".into());
        }
        if self.colors.as_ref().is_some_and(|v| v.len() != n) {
            return Err("colour count differs from vertex count".into());
        }
        Ok(())
    }

    /// The three corners of triangle `t`.
    #[inline]
    pub fn triangle(&self, t: usize) -> [Vec3; 3] {
        self.indices[t].map(|i| self.positions[i as usize])
    }

    /// Unit normal of triangle `t` (zero for a degenerate triangle).
    pub fn face_normal(&self, t: usize) -> Vec3 {
        let [a, b, c] = self.triangle(t);
        (b - a).cross(c - a).normalize_or_zero()
    }

    /// Total surface area.
    pub fn area(&self) -> f64 {
        (0..self.indices.len())
            .map(|t| {
                let [a, b, c] = self.triangle(t);
                0.5 * (b - a).as_dvec3().cross((c - a).as_dvec3()).length()
            })
            .sum()
    }

    /// Axis-aligned bounds `(min, max)`; `None` for an empty mesh.
    pub fn bounds(&self) -> Option<(Vec3, Vec3)> {
        let first = *self.positions.first()?;
        Some(self.positions.iter().fold((first, first), |(lo, hi), p| (lo.min(*p), hi.max(*p))))
    }

    /// Area-weighted vertex normals from the faces (sets `self.normals`).
    pub fn compute_vertex_normals(&mut self) {
        let mut acc = vec![Vec3::ZERO; self.positions.len()];
        for f in &self.indices {
            let [a, b, c] = f.map(|i| self.positions[i as usize]);
            let n = (b - a).cross(c - a); // length = 2 * area: area weighting
            for &i in f {
                acc[i as usize] += n;
            }
        }
        self.normals = Some(acc.into_iter().map(Vec3::normalize_or_zero).collect());
    }

    /// Appends another mesh (indices are offset).
    pub fn append(&mut self, other: &TriMesh) {
        let off = self.positions.len() as u32;
        let both_n = self.normals.is_some() && other.normals.is_some();
        let both_c = self.colors.is_some() && other.colors.is_some();
        let empty = self.positions.is_empty();
        self.positions.extend_from_slice(&other.positions);
        self.indices.extend(other.indices.iter().map(|f| f.map(|i| i + off)));
        if both_n || (empty && other.normals.is_some()) {
            self.normals.get_or_insert_with(Vec::new).extend_from_slice(other.normals.as_ref().unwrap());
        } else {
            self.normals = None;
        }
        if both_c || (empty && other.colors.is_some()) {
            self.colors.get_or_insert_with(Vec::new).extend_from_slice(other.colors.as_ref().unwrap());
        } else {
            self.colors = None;
        }
    }

    /// Applies an affine 4x4 transform to positions (and its normal matrix to normals).
    pub fn transform(&mut self, m: &glam::Mat4) {
        for p in &mut self.positions {
            *p = m.transform_point3(*p);
        }
        if let Some(ns) = &mut self.normals {
            let nm = glam::Mat3::from_mat4(*m).inverse().transpose();
            for n in ns {
                *n = (nm * *n).normalize_or_zero();
            }
        }
    }

    /// A parry3d mesh (with its BVH) for ray casting and point projection.
    pub fn to_parry(&self) -> Result<parry3d::shape::TriMesh, InvalidMesh> {
        self.validate()?;
        parry3d::shape::TriMesh::new(self.positions.clone(), self.indices.clone())
            .map_err(|e| InvalidMesh(format!("{e:?}")))
    }
}
