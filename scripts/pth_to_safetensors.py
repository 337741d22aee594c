#!/usr/bin/env python3
"""Convert an official Dens3R / DUSt3R / MASt3R `.pth` checkpoint to safetensors for dens3r.

    python3 scripts/pth_to_safetensors.py MODEL.pth [OUT.safetensors]

Needs `torch` and `safetensors` (pip install torch safetensors). Writes OUT.safetensors (the
state_dict, every tensor contiguous and unshared) and OUT.json ({"args": <the constructor
string stored in the checkpoint>}). The input is only read.

Optional: `dens3r convert MODEL.pth -o DIR` does the same natively (no PyTorch, and nothing in the
pickle is executed), writing DIR/model.safetensors and DIR/config.json.
"""
import json
import sys
from pathlib import Path

import torch
from safetensors.torch import save_file


def main() -> int:
    if len(sys.argv) not in (2, 3):
        print(__doc__)
        return 2
    src = Path(sys.argv[1])
    dst = Path(sys.argv[2]) if len(sys.argv) == 3 else src.with_suffix(".safetensors")
    ckpt = torch.load(src, map_location="cpu", weights_only=False)
    state = ckpt["model"] if isinstance(ckpt, dict) and "model" in ckpt else ckpt
    tensors = {k: v.detach().contiguous().clone() for k, v in state.items() if torch.is_tensor(v)}
    tmp = dst.with_suffix(dst.suffix + ".tmp")
    save_file(tensors, str(tmp))
    tmp.replace(dst)
    args = getattr(ckpt.get("args"), "model", None) if isinstance(ckpt, dict) else None
    dst.with_suffix(".json").write_text(json.dumps({"args": args}, indent=1))
    print(f"wrote {dst} ({len(tensors)} tensors)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
