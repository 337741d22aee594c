//! Why an image, a device or a reference dump could not be used: one line naming the file or
//! the setting and what to do.

dens3r_io::file_or_setting_error! {
    /// A dens3r-backbone failure outside the checkpoint readers (which give
    /// [`crate::WeightsError`]).
    BackboneError;
    files: [
        crate::weights::WeightsError,
        crate::onnx::OnnxError,
        dens3r_scene::SceneError,
        dens3r_io::IoError,
    ];
    plain: [];
}
