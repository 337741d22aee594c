#!/usr/bin/env python3
"""One Dens3R training step in PyTorch, written from shared/docs/model-spec.md section 5, for
`dens3r bench train`: the network of bench/torch_dens3r.py with every weight a trainable leaf,
the stage's losses (ConfLoss(Regr3D) with 'avg_dis', the pointmap-normal loss, MASt3R's InfoNCE
'proper' matching with confidence weighting, the normal L1), global-norm clipping and AdamW, on
the batch and initial weights the Rust side wrote into DIR. Prints JSON: per-step seconds and
loss terms, peak RSS.

    python3 bench/torch_dens3r_train.py DIR --threads 2
"""
import argparse
import json
import math
import os
import resource
import sys
import time

import numpy as np
import torch
from safetensors.torch import load_file

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from torch_dens3r import Dens3r  # noqa: E402


def avg_dis(p1, p2, v1, v2):
    """Both views divided by the mean norm over the valid pixels of both (per sample)."""
    s = (p1.norm(dim=-1) * v1).sum((1, 2)) + (p2.norm(dim=-1) * v2).sum((1, 2))
    f = (s / (v1.sum((1, 2)) + v2.sum((1, 2)) + 1e-8)).clamp(min=1e-8)[:, None, None, None]
    return p1 / f, p2 / f


def masked_mean(x, m):
    return (x * m).sum() / m.sum().clamp(min=1)


def conf_regr3d(pred, conf, gt, valid, alpha):
    p1, p2 = avg_dis(pred[0], pred[1], valid[0], valid[1])
    g1, g2 = avg_dis(gt[0], gt[1], valid[0], valid[1])
    tot = 0
    for p, g, c, v in [(p1, g1, conf[0], valid[0]), (p2, g2, conf[1], valid[1])]:
        tot = tot + masked_mean((p - g).norm(dim=-1) * c - alpha * c.log(), v)
    return tot


def pcd2normal(p):
    a = p[:, 1:-1, 2:] - p[:, 1:-1, :-2]
    b = p[:, :-2, 1:-1] - p[:, 2:, 1:-1]
    n = torch.cross(a, b, dim=-1)
    n = torch.stack([n[..., 0], -n[..., 1], n[..., 2]], dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    return torch.nn.functional.pad(n, (0, 0, 1, 1, 1, 1))


def normal_l1(pred, gt, valid):
    m = valid * (gt.abs().sum(-1) > 0).float()
    return masked_mean((pred - gt).abs().sum(-1), m)


def matching(desc, dconf, matches, tau, alpha):
    b, h, w, d = desc[0].shape
    terms, count = [], 0
    for s in range(b):
        sel = matches[matches[:, 0] == s]
        if len(sel) == 0:
            continue
        i1, i2 = sel[:, 1], sel[:, 2]
        a = desc[0][s].reshape(h * w, d)[i1]
        bb = desc[1][s].reshape(h * w, d)[i2]
        sim = a @ bb.T / tau
        diag = sim.diagonal()
        floor = math.log(1e-8)
        l = -((diag - sim.logsumexp(1)).clamp(min=floor) + (diag - sim.logsumexp(0)).clamp(min=floor))
        c = (dconf[0][s].reshape(-1)[i1] + dconf[1][s].reshape(-1)[i2]) / 2
        terms.append((l * c - alpha * c.log()).sum())
        count += len(sel)
    return sum(terms) / count if count else None


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("dir")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    cfg = json.load(open(os.path.join(a.dir, "bench.json")))
    ld = lambda n: torch.from_numpy(np.load(os.path.join(a.dir, n + ".npy")))
    img1, img2 = ld("img1"), ld("img2")
    gt, valid = [ld("gt1"), ld("gt2")], [ld("valid1"), ld("valid2")]
    n_in1, n_own = [ld("n_in1_1"), ld("n_in1_2")], [ld("n_own_1"), ld("n_own_2")]
    matches = ld("matches").long()
    params = {k: v.clone().requires_grad_(True) for k, v in load_file(os.path.join(a.dir, "init.safetensors")).items()}
    model = Dens3r(params, cfg["enc_heads"], cfg["dec_heads"])
    decay = [p for p in params.values() if p.ndim >= 2]
    rest = [p for p in params.values() if p.ndim < 2]
    opt = torch.optim.AdamW(
        [{"params": decay, "weight_decay": cfg["weight_decay"]}, {"params": rest, "weight_decay": 0.0}],
        lr=cfg["lrs"][0], betas=(0.9, 0.999), eps=1e-8,
    )
    w_glb, w_n, w_match, w_normal = cfg["weights"]
    steps = []
    for step, lr in enumerate(cfg["lrs"]):
        for g in opt.param_groups:
            g["lr"] = lr
        t0 = time.perf_counter()
        # Like the Rust side, only the heads the stage's losses read.
        (p1, c1, d1, nr1, dc1), (p2, c2, d2, nr2, dc2) = model.forward(img1, img2, normal=w_normal > 0, desc=w_match > 0)
        pts_glb = conf_regr3d([p1, p2], [c1, c2], gt, valid, cfg["alpha"])
        pts_n = normal_l1(pcd2normal(p1), n_in1[0], valid[0]) + normal_l1(pcd2normal(p2), n_in1[1], valid[1])
        total = w_glb * pts_glb + w_n * pts_n
        terms = {"pts_glb": pts_glb.item(), "pts_n": pts_n.item()}
        if w_match > 0:
            m = matching([d1, d2], [dc1, dc2], matches, cfg["match_temperature"], cfg["match_alpha"])
            if m is not None:
                total = total + w_match * m
                terms["match"] = m.item()
        if w_normal > 0:
            n = normal_l1(nr1, n_own[0], valid[0]) + normal_l1(nr2, n_own[1], valid[1])
            total = total + w_normal * n
            terms["n"] = n.item()
        opt.zero_grad(set_to_none=True)
        total.backward()
        norm = torch.nn.utils.clip_grad_norm_(list(params.values()), cfg["clip"]) if cfg["clip"] > 0 else torch.tensor(0.0)
        opt.step()
        terms.update(loss=total.item(), grad_norm=float(norm), seconds=time.perf_counter() - t0)
        steps.append(terms)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"steps": steps, "peak_rss_mb": rss, "threads": a.threads, "torch": torch.__version__}))


if __name__ == "__main__":
    main()
