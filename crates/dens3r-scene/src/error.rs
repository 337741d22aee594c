//! The scene-folder error.

dens3r_io::file_error! {
    /// A scene-folder problem: the file concerned and what to do about it (one line).
    SceneError;
    from: [dens3r_mesh::MeshError, dens3r_io::IoError];
}
