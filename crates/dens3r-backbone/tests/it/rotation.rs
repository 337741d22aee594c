//! The portrait round trip (spec 3.2 rotate_recover) against independent renders: a pointmap
//! seen by the landscape camera the network runs on, rotated back, must equal the pointmap
//! rendered by the physically rotated portrait camera.

use dens3r_backbone::preprocess::{rotate_map_clockwise, unrotate_vector};
use dens3r_geom::camera::look_at;
use dens3r_geom::pointmap::depth_to_pointmap;
use dens3r_geom::{DMat3, DMat4, DVec3, Intrinsics, PinholeCamera};
use dens3r_render::procedural::room;
use dens3r_render::World;

#[test]
fn rotated_back_pointmap_equals_the_portrait_camera_render() {
    let world = World::new(room(2)).unwrap();
    let (wl, hl) = (64usize, 48usize);
    let kl = Intrinsics { fx: 50.0, fy: 50.0, cx: 32.0, cy: 24.0 };
    let c2w_l = look_at(DVec3::new(0.2, -0.3, 1.4), DVec3::new(1.5, 1.0, 1.0), DVec3::Z).unwrap();
    let land = PinholeCamera { intrinsics: kl, width: wl, height: hl, cam_to_world: c2w_l };
    // The portrait image is the landscape one rotated clockwise; its camera frame satisfies
    // p_portrait = Rz(+90) p_landscape, and pixel (u, v) of the landscape image lands at
    // (H_l - 1 - v, u) of the portrait image.
    let rz = DMat3::from_cols(DVec3::new(0.0, 1.0, 0.0), DVec3::new(-1.0, 0.0, 0.0), DVec3::Z);
    let r_p = DMat3::from_mat4(c2w_l) * rz.transpose();
    let c2w_p = DMat4::from_mat3_translation(r_p, c2w_l.w_axis.truncate());
    let kp = Intrinsics { fx: 50.0, fy: 50.0, cx: (hl - 1) as f64 - kl.cy, cy: kl.cx };
    let port = PinholeCamera { intrinsics: kp, width: hl, height: wl, cam_to_world: c2w_p };

    let pl = depth_to_pointmap(&world.render(&land).depth, &kl);
    let pp = depth_to_pointmap(&world.render(&port).depth, &kp);
    let flat: Vec<f32> = pl.data().iter().flat_map(|p| p.to_array()).collect();
    let (back, h, w) = rotate_map_clockwise(&flat, hl, wl, 3);
    assert_eq!((w, h), (hl, wl));
    let mut worst = 0.0f32;
    for (i, c) in back.chunks_exact(3).enumerate() {
        let ours = glam::Vec3::from_array(unrotate_vector([c[0], c[1], c[2]]));
        worst = worst.max((ours - pp.data()[i]).length() / pp.data()[i].length());
    }
    assert!(worst < 1e-5, "relative error {worst}");
}
