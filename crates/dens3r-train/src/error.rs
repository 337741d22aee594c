//! Why training, its data or its outputs could not go on: one line naming the file or the
//! setting and what to do.

dens3r_io::file_or_setting_error! {
    /// A dens3r-train failure. Errors that carry no file (serialisation, a raster of the wrong
    /// size, a failed write to an open log) keep their message.
    TrainError;
    files: [
        dens3r_scene::SceneError,
        dens3r_mesh::MeshError,
        dens3r_backbone::weights::WeightsError,
        dens3r_io::IoError,
    ];
    plain: [std::io::Error, serde_json::Error, dens3r_geom::RasterError, dens3r_render::WorldError];
}
