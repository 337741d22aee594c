#!/usr/bin/env python3
"""Dens3R forward in PyTorch, written from shared/docs/model-spec.md sections 1.2-1.6, for
`dens3r bench backbone`: loads the same safetensors the Rust side uses, times one pair forward
and prints JSON {"seconds", "peak_rss_mb", "max_abs_diff"?}; on CUDA (`--device cuda`) also
"peak_device_mb" (the caching allocator's peak reserved bytes), in `--dtype` float32, float16
or bfloat16.

    python3 bench/torch_dens3r.py WEIGHTS.safetensors --size 512x384 --threads 2 \
        [--heads 16,12] [--image img.npy --compare rust_pts3d.npy] [--device cuda --dtype float16]
"""
import argparse
import json
import resource
import time

import numpy as np
import torch
import torch.nn.functional as F
from safetensors.torch import load_file


def rope_tables(h, w, head_dim, base=100.0, interpolate=True):
    pos = torch.cartesian_prod(torch.arange(h), torch.arange(w))  # (N, 2) = (row, col)
    d = head_dim // 2
    inv = 1.0 / (base ** (torch.arange(0, d, 2).float() / d))
    s = int(pos.max()) + 1
    t = torch.arange(s, dtype=torch.float32)
    if interpolate:
        t = t * 32 / s
    freqs = torch.cat([torch.einsum("i,j->ij", t, inv)] * 2, dim=-1)
    cos, sin = freqs.cos(), freqs.sin()
    return cos[pos[:, 0]], sin[pos[:, 0]], cos[pos[:, 1]], sin[pos[:, 1]]


def rope(x, tab):
    cy, sy, cx, sx = tab
    y, xx = x.chunk(2, dim=-1)

    def rot(t, c, s):
        a, b = t.chunk(2, dim=-1)
        return t * c + torch.cat([-b, a], dim=-1) * s

    return torch.cat([rot(y, cy, sy), rot(xx, cx, sx)], dim=-1)


class Dens3r:
    def __init__(self, w, enc_heads, dec_heads):
        self.w, self.eh, self.dh = w, enc_heads, dec_heads
        self.enc_depth = len({k.split(".")[1] for k in w if k.startswith("enc_blocks.")})
        self.dec_depth = len({k.split(".")[1] for k in w if k.startswith("dec_blocks.")})
        self.shared = not any(k.startswith("dec_blocks2.") for k in w)
        self.patch = w["patch_embed.proj.weight"].shape[-1]

    def lin(self, x, p):
        return F.linear(x, self.w[p + ".weight"], self.w.get(p + ".bias"))

    def ln(self, x, p):
        return F.layer_norm(x, x.shape[-1:], self.w[p + ".weight"], self.w[p + ".bias"], eps=1e-6)

    def mlp(self, x, p):
        return self.lin(F.gelu(self.lin(x, p + ".fc1")), p + ".fc2")

    def self_attn(self, x, p, heads, tab):
        b, n, d = x.shape
        qkv = self.lin(x, p + ".qkv").reshape(b, n, 3, heads, d // heads).permute(2, 0, 3, 1, 4)
        q, k, v = rope(qkv[0], tab), rope(qkv[1], tab), qkv[2]
        o = F.scaled_dot_product_attention(q, k, v)
        return self.lin(o.transpose(1, 2).reshape(b, n, d), p + ".proj")

    def cross_attn(self, x, y, p, heads, tq, tk):
        b, n, d = x.shape
        split = lambda t: t.reshape(b, t.shape[1], heads, d // heads).transpose(1, 2)
        q = rope(split(self.lin(x, p + ".projq")), tq)
        k = rope(split(self.lin(y, p + ".projk")), tk)
        v = split(self.lin(y, p + ".projv"))
        o = F.scaled_dot_product_attention(q, k, v)
        return self.lin(o.transpose(1, 2).reshape(b, n, d), p + ".proj")

    def encode(self, img):
        h, w = img.shape[2] // self.patch, img.shape[3] // self.patch
        x = F.conv2d(img, self.w["patch_embed.proj.weight"], self.w["patch_embed.proj.bias"], stride=self.patch)
        x = x.flatten(2).transpose(1, 2)
        tab = [t.to(x.device, x.dtype) for t in rope_tables(h, w, x.shape[-1] // self.eh)]
        for i in range(self.enc_depth):
            p = f"enc_blocks.{i}"
            x = x + self.self_attn(self.ln(x, p + ".norm1"), p + ".attn", self.eh, tab)
            x = x + self.mlp(self.ln(x, p + ".norm2"), p + ".mlp")
        return self.ln(x, "enc_norm"), (h, w)

    def dec_block(self, x, y, p, tx, ty):
        x = x + self.self_attn(self.ln(x, p + ".norm1"), p + ".attn", self.dh, tx)
        yn = self.ln(y, p + ".norm_y")
        x = x + self.cross_attn(self.ln(x, p + ".norm2"), yn, p + ".cross_attn", self.dh, tx, ty)
        return x + self.mlp(self.ln(x, p + ".norm3"), p + ".mlp")

    def conv(self, x, p, stride=1, bias=True):
        wt = self.w[p + ".weight"]
        return F.conv2d(x, wt, self.w[p + ".bias"] if bias else None, stride=stride, padding=wt.shape[-1] // 2)

    def dpt(self, layers, grid, p):
        h, w = grid
        maps = []
        for i, t in enumerate(layers):
            x = t.transpose(1, 2).reshape(t.shape[0], t.shape[2], h, w)
            x = self.conv(x, f"{p}.act_postprocess.{i}.0")
            if i < 2:
                wt = self.w[f"{p}.act_postprocess.{i}.1.weight"]
                x = F.conv_transpose2d(x, wt, self.w[f"{p}.act_postprocess.{i}.1.bias"], stride=wt.shape[-1])
            if i == 3:
                x = self.conv(x, f"{p}.act_postprocess.3.1", stride=2)
            maps.append(self.conv(x, f"{p}.scratch.layer{i + 1}_rn", bias=False))

        def rcu(x, q):
            return self.conv(F.relu(self.conv(F.relu(x), q + ".conv1")), q + ".conv2") + x

        def fuse(i, x, skip=None):
            q = f"{p}.scratch.refinenet{i}"
            if skip is not None:
                x = x + rcu(skip, q + ".resConfUnit1")
            x = rcu(x, q + ".resConfUnit2")
            x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True)
            return self.conv(x, q + ".out_conv")

        p4 = fuse(4, maps[3])[:, :, : maps[2].shape[2], : maps[2].shape[3]]
        p3 = fuse(3, p4, maps[2])
        p2 = fuse(2, p3, maps[1])
        p1 = fuse(1, p2, maps[0])
        x = F.interpolate(self.conv(p1, f"{p}.head.0"), scale_factor=2, mode="bilinear", align_corners=True)
        return self.conv(F.relu(self.conv(x, f"{p}.head.2")), f"{p}.head.4")

    def decode(self, e1, g1, e2, g2):
        """Both views' decoder outputs (every block; the last through dec_norm)."""
        dd = self.w["decoder_embed.weight"].shape[0]
        t1, t2 = ([t.to(e1.device, e1.dtype) for t in rope_tables(*g, dd // self.dh)] for g in (g1, g2))
        f1, f2 = self.lin(e1, "decoder_embed"), self.lin(e2, "decoder_embed")
        out1, out2 = [], []
        for i in range(self.dec_depth):
            b2 = f"dec_blocks.{i}" if self.shared else f"dec_blocks2.{i}"
            f1, f2 = self.dec_block(f1, f2, f"dec_blocks.{i}", t1, t2), self.dec_block(f2, f1, b2, t2, t1)
            out1.append(f1)
            out2.append(f2)
        out1[-1], out2[-1] = self.ln(out1[-1], "dec_norm"), self.ln(out2[-1], "dec_norm")
        return out1, out2

    def hooked(self, e, outs):
        L = self.dec_depth
        lay = [e] + outs
        return [lay[i] for i in [0, L * 2 // 4, L * 3 // 4, L]]

    def pointmap(self, e, outs, g, head):
        raw = self.dpt(self.hooked(e, outs), g, head + ".dpt").permute(0, 2, 3, 1)
        v = raw[..., :3]
        d = v.norm(dim=-1, keepdim=True)
        return v / d.clamp(min=1e-8) * torch.expm1(d), 1 + raw[..., 3].exp()

    def descriptors(self, e, outs, g, head, conf):
        feat = self.mlp(torch.cat([e, outs[-1]], dim=-1), head + ".head_local_features")
        feat = F.pixel_shuffle(feat.transpose(1, 2).reshape(feat.shape[0], -1, *g), self.patch).permute(0, 2, 3, 1)
        desc_t = feat[..., :24] / feat[..., :24].norm(dim=-1, keepdim=True)
        # desc_conf: exp of the 25th channel (MASt3R), else a copy of conf.
        return desc_t, feat[..., 24].exp() if feat.shape[-1] > 24 else conf

    def normals(self, e, outs, g):
        nrm = self.dpt(self.hooked(e, outs), g, "normal_local_head.dpt").permute(0, 2, 3, 1).clamp(-1, 1)
        return nrm / nrm.norm(dim=-1, keepdim=True).clamp(min=1e-12)

    def forward(self, img1, img2, normal=True, desc=True):
        """Both views' (pts, conf, desc, normal, desc_conf); normal / desc False skip those heads (None)."""
        (e1, g1), (e2, g2) = self.encode(img1), self.encode(img2)
        out1, out2 = self.decode(e1, g1, e2, g2)
        res = []
        for e, outs, g, head in [(e1, out1, g1, "ptsmatch_local_head"), (e2, out2, g2, "ptsmatch_global_head")]:
            pts, conf = self.pointmap(e, outs, g, head)
            desc_t, desc_conf = self.descriptors(e, outs, g, head, conf) if desc else (None, None)
            nrm = self.normals(e, outs, g) if normal else None
            res.append((pts, conf, desc_t, nrm, desc_conf))
        return res

    def stages(self, img1, img2):
        """The forward as (name, thunk) stages in order, each run on the previous ones' results
        (the same stages and names as the Rust side's profile)."""
        st = {}
        views = [("ptsmatch_local_head", 0), ("ptsmatch_global_head", 1)]

        def encoder():
            st["e"] = [self.encode(img1), self.encode(img2)]

        def decoder():
            (e1, g1), (e2, g2) = st["e"]
            st["d"] = self.decode(e1, g1, e2, g2)

        def pointmap():
            st["p"] = [self.pointmap(st["e"][i][0], st["d"][i], st["e"][i][1], h) for h, i in views]

        def normal():
            [self.normals(st["e"][i][0], st["d"][i], st["e"][i][1]) for _, i in views]

        def desc():
            [self.descriptors(st["e"][i][0], st["d"][i], st["e"][i][1], h, st["p"][i][1]) for h, i in views]

        return [("encoder", encoder), ("decoder", decoder), ("pointmap", pointmap), ("normal", normal), ("desc", desc)]


def sync(device):
    """Waits for the device's queued work (CUDA runs asynchronously)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def profile(model, img, img2, repeat, device):
    """Per stage: fastest seconds of `repeat` runs, and FLOPs (torch's FlopCounterMode: matmuls,
    convolutions, attention; 2 per multiply-add) of one run; plus this machine's f32 GEMM rate."""
    from torch.utils.flop_counter import FlopCounterMode

    secs, flops = {}, {}
    for r in range(max(1, repeat) + 1):
        for name, run in model.stages(img, img2):
            if r == 0:  # the counting pass (slower: every op is intercepted)
                with FlopCounterMode(display=False) as fc:
                    run()
                flops[name] = fc.get_total_flops()
            else:
                sync(device)
                t0 = time.perf_counter()
                run()
                sync(device)
                secs[name] = min(secs.get(name, float("inf")), time.perf_counter() - t0)
    n, k = (8192, 20) if device.type == "cuda" else (2048, 5)
    a, b = torch.rand(n, n, device=device, dtype=img.dtype), torch.rand(n, n, device=device, dtype=img.dtype)
    torch.mm(a, b)
    sync(device)
    t0 = time.perf_counter()
    for _ in range(k):
        torch.mm(a, b)
    sync(device)
    gemm = k * 2 * n**3 / (time.perf_counter() - t0)
    return {"seconds": secs, "flops": flops, "gemm_flops_per_s": gemm}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("weights")
    ap.add_argument("--size", default="512x384")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--heads", default="16,12")
    ap.add_argument("--image", help="(1, 3, H, W) input in [-1, 1]; random if absent")
    ap.add_argument("--image2", help="second view (default: the first image again)")
    ap.add_argument("--repeat", type=int, default=1, help="forward passes; the fastest is reported")
    ap.add_argument("--compare", help="view-1 pts3d (H, W, 3) from the Rust side")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--profile", action="store_true", help="also time and count FLOPs per stage (after the timed passes)")
    ap.add_argument("--device", default="cpu", help="cpu or cuda[:N]")
    ap.add_argument("--dtype", default="float32", choices=["float32", "float16", "bfloat16"])
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    device, dtype = torch.device(a.device), getattr(torch, a.dtype)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("PyTorch sees no CUDA device (a CPU-only torch, or no NVIDIA driver)")
    wd, ht = (int(v) for v in a.size.split("x"))
    eh, dh = (int(v) for v in a.heads.split(","))
    model = Dens3r({k: v.to(device, dtype) for k, v in load_file(a.weights).items()}, eh, dh)
    img = torch.from_numpy(np.load(a.image)) if a.image else torch.rand(1, 3, ht, wd) * 2 - 1
    img2 = torch.from_numpy(np.load(a.image2)) if a.image2 else img
    img, img2 = img.to(device, dtype), img2.to(device, dtype)
    times = []
    with torch.inference_mode():
        # On a GPU the first pass pays for kernel selection and the allocator's growth.
        for _ in range(max(1, a.repeat) + (device.type == "cuda")):
            sync(device)
            t0 = time.perf_counter()
            res = model.forward(img, img2)
            sync(device)
            times.append(time.perf_counter() - t0)
    if device.type == "cuda":
        times = times[1:]
    out = {"seconds": min(times), "all_seconds": times, "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "threads": a.threads, "torch": torch.__version__, "device": str(device), "dtype": a.dtype}
    if device.type == "cuda":
        out["peak_device_mb"] = torch.cuda.max_memory_reserved(device) / 2**20
        out["device_name"] = torch.cuda.get_device_name(device)
    if a.compare:
        ref = np.load(a.compare)
        out["max_abs_diff_pts3d"] = float(np.abs(res[0][0].float().cpu().numpy() - ref).max())
        out["max_abs_pts3d"] = float(np.abs(ref).max())
    if a.profile:
        with torch.inference_mode():
            out["profile"] = profile(model, img, img2, a.repeat, device)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
