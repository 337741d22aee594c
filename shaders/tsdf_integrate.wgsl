// Sparse voxel-block TSDF integration of one depth frame (dens3r-fusion's GPU path).
//
// Mirrors `SparseTsdf::integrate` on the CPU voxel for voxel: the host allocates blocks and
// sends, per touched block, the camera-frame centre of its first voxel (xyz) and its pool slot
// (w, bit-cast); one invocation updates one voxel. Voxel i of a block is (x, y, z) with
// i = x + 8 y + 64 z. Invalid depths arrive as -1 and invalid weights as 0, so no NaN tests are
// needed here (GPU compilers may fold them away).

struct Params {
    // Camera-frame steps of one voxel along world x, y, z.
    ax: vec4<f32>,
    ay: vec4<f32>,
    az: vec4<f32>,
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    width: u32,
    height: u32,
    n_blocks: u32,
    // bit 0: per-pixel weights; bit 1: colour.
    flags: u32,
    trunc: f32,
    max_weight: f32,
    dmin: f32,
    dmax: f32,
}

@group(0) @binding(0) var<uniform> prm: Params;
@group(0) @binding(1) var<storage, read> blocks: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> depth: array<f32>;
@group(0) @binding(3) var<storage, read> weight: array<f32>;
@group(0) @binding(4) var<storage, read> rgb: array<u32>;
// (normalised tsdf, weight) per voxel, slot-major.
@group(0) @binding(5) var<storage, read_write> vox: array<vec2<f32>>;
// Average colour, 3 floats per voxel.
@group(0) @binding(6) var<storage, read_write> col: array<f32>;

@compute @workgroup_size(256)
fn integrate(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) li: u32,
) {
    let g = (wid.y * nwg.x + wid.x) * 256u + li;
    let b = g / 512u;
    if (b >= prm.n_blocks) {
        return;
    }
    let vi = g % 512u;
    let x = f32(vi % 8u);
    let y = f32((vi / 8u) % 8u);
    let z = f32(vi / 64u);
    let e = blocks[b];
    let row = e.xyz + prm.az.xyz * z + prm.ay.xyz * y;
    let pc = row + prm.ax.xyz * x;
    if (pc.z <= 0.0) {
        return;
    }
    let inv_z = 1.0 / pc.z;
    let u = prm.fx * pc.x * inv_z + prm.cx;
    let v = prm.fy * pc.y * inv_z + prm.cy;
    // Nearest pixel; the range test keeps the truncating casts exact rounding.
    if (!(u >= -0.5 && v >= -0.5 && u < f32(prm.width) - 0.5 && v < f32(prm.height) - 0.5)) {
        return;
    }
    let idx = u32(v + 0.5) * prm.width + u32(u + 0.5);
    let d = depth[idx];
    if (!(d >= prm.dmin && d <= prm.dmax)) {
        return;
    }
    let sdf = d - pc.z;
    if (sdf < -prm.trunc) {
        return;
    }
    var ow = 1.0;
    if ((prm.flags & 1u) != 0u) {
        ow = weight[idx];
        if (!(ow > 0.0)) {
            return;
        }
    }
    let obs = min(sdf / prm.trunc, 1.0);
    let k = bitcast<u32>(e.w) * 512u + vi;
    let old = vox[k];
    let w0 = old.y;
    let wn = w0 + ow;
    let inv = 1.0 / wn;
    vox[k] = vec2<f32>((old.x * w0 + obs * ow) * inv, min(wn, prm.max_weight));
    if ((prm.flags & 2u) != 0u) {
        let c = rgb[idx];
        let px = vec3<f32>(f32(c & 255u), f32((c >> 8u) & 255u), f32((c >> 16u) & 255u));
        for (var ch = 0u; ch < 3u; ch++) {
            let j = 3u * k + ch;
            col[j] = (col[j] * w0 + px[ch] * ow) * inv;
        }
    }
}
