"""A PyTorch segmentation head trained on dens3r's frozen features (Model.features).

Trains a small conv head on the bundled rendered room's labelled views and scores held-out
views. Run: python python/examples/train_seg_head.py   (needs torch and pillow)
"""
import json, pathlib
import numpy as np, torch, torch.nn.functional as F
from PIL import Image
import dens3r

root = pathlib.Path(__file__).resolve().parents[2] / "data-samples"
classes = json.loads((root / "room" / "classes.json").read_text())
model = dens3r.Model.load()  # the bundled dens3r-s; Model.load("dust3r-512-dpt") for an official one
data = []
for scene in ["room", "orbit"]:
    s = dens3r.read_scene(root / scene)
    for name, img in zip(s["names"], s["images"]):
        feats = torch.from_numpy(np.concatenate(model.features(img, size=224)))  # (C, h, w)
        label = np.array(Image.open(root / scene / "labels" / f"{name}.png"))
        data.append((feats, torch.from_numpy(label.astype(np.int64))))
train, test = data[::4] + data[1::4] + data[2::4], data[3::4]  # every fourth view held out
k, c = len(classes), data[0][0].shape[0]
head = torch.nn.Sequential(torch.nn.Conv2d(c, 128, 3, padding=1), torch.nn.GELU(), torch.nn.Conv2d(128, k, 1))
opt = torch.optim.AdamW(head.parameters(), lr=1e-3)
def logits(f, size):  # features -> per-pixel class scores at the label's size
    return F.interpolate(head(f[None]), size=size, mode="bilinear", align_corners=False)
for epoch in range(60):
    loss = sum(F.cross_entropy(logits(f, l.shape), l[None], ignore_index=255) for f, l in train) / len(train)
    opt.zero_grad(); loss.backward(); opt.step()
with torch.no_grad():
    pred = torch.cat([logits(f, l.shape).argmax(1).flatten() for f, l in test])
    gt = torch.cat([l.flatten() for _, l in test])
ious = [((pred == i) & (gt == i)).sum() / ((pred == i) | (gt == i)).sum() for i in range(k) if (gt == i).any()]
print(f"{len(train)} training views, {len(test)} held out; final loss {loss.item():.3f}")
print(f"held-out pixel accuracy {(pred == gt)[gt != 255].float().mean():.3f}, mIoU {torch.stack(ious).mean():.3f}")
