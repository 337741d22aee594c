//! Why a head could not be trained, loaded or run: one line naming the file or the setting and
//! what to do.

dens3r_io::file_or_setting_error! {
    /// A dens3r-heads failure.
    HeadsError;
    files: [
        dens3r_scene::SceneError,
        dens3r_mesh::MeshError,
        dens3r_backbone::weights::WeightsError,
        dens3r_backbone::onnx::OnnxError,
        dens3r_io::IoError,
    ];
    plain: [];
}
