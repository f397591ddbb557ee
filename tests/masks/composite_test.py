#!/usr/bin/python3
"""The training script's environment compositing (train_masks.composite):
inside the rock's silhouette the photo is the rig's rock (recoloured, its
grain kept, nothing of the turntable showing), far from it the
empty-turntable photo untouched, and the drawn shadow only ever darkens the
turntable. Exit 77 (skip) without
Debian's python3-torch and python3-opencv."""

import os
import sys

try:
    import torch
    import cv2  # noqa: F401  (the script imports it)
except ImportError as e:
    print("composite_test: skipped, %s (apt-get install python3-torch python3-opencv)" % e)
    sys.exit(77)

here = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(here, "..", "..", "scripts", "masks"))
import train_masks as tm  # noqa: E402

failures = []


def check(cond, what):
    if not cond:
        failures.append(what)
        print("FAIL: " + what)


torch.manual_seed(0)
gen = torch.Generator().manual_seed(3)
n, H, W = 16, 120, 160
# A textured rock (a disc of random grey levels) on a white photo.
yy, xx = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
disc = (((yy - 60) ** 2 + (xx - 80) ** 2) < 30 ** 2).float()
img = torch.ones(n, 3, H, W)
rock = torch.rand(n, 3, H, W) * 0.5 + 0.25
img = img * (1 - disc) + rock * disc
mask = disc.expand(n, 1, H, W).clone()
# An empty turntable: a wood-like pattern.
bg = ((torch.sin(xx.float() / 3.0) * 0.2 + 0.5) * 255).to(torch.uint8)
bgs = torch.stack([bg, (bg.float() * 0.8).to(torch.uint8), (bg.float() * 0.5).to(torch.uint8)]).unsqueeze(0)

out = tm.composite(img, mask, bgs, gen, 1.0)
check(out.shape == img.shape, "the batch keeps its shape")
check(bool(torch.isfinite(out).all()) and float(out.min()) >= 0 and float(out.max()) <= 1,
      "the composite is finite and within 0..1")
inner = disc > 0
b = bgs[0].float() / 255.0
# The same draw onto another turntable: inside the silhouette nothing changes.
other = tm.composite(img, mask, 255 - bgs, torch.Generator().manual_seed(3), 1.0)
lum = lambda x: 0.299 * x[0] + 0.587 * x[1] + 0.114 * x[2]
for i in range(n):
    inside_change = float((other[i][:, inner] - out[i][:, inner]).abs().max())
    check(inside_change < 1e-6, "photo %d: inside the silhouette the turntable does not show (%.2g)"
          % (i, inside_change))
    # Inside: the rock recoloured, its grain kept (where it did not clip).
    sel = inner & (out[i].max(dim=0).values < 0.999) & (out[i].min(dim=0).values > 0.001)
    a, c = lum(out[i])[sel], lum(img[i])[sel]
    corr = float(((a - a.mean()) * (c - c.mean())).mean() / (a.std() * c.std() + 1e-9))
    check(corr > 0.9, "photo %d: inside the silhouette the rock's grain is kept (correlation %.3f)" % (i, corr))
    # Outside: the empty turntable, darkened where the shadow fell, never
    # brightened, and untouched somewhere.
    outside = disc == 0
    d = out[i][:, outside] - b[:, outside]
    check(float(d.max()) < 1e-4, "photo %d: the shadow only darkens (max +%.3g)" % (i, float(d.max())))
    untouched = float((d.abs().max(dim=0).values < 1e-4).float().mean())
    check(untouched > 0.3, "photo %d: most of the turntable is untouched (%.2f)" % (i, untouched))
# At probability 0 nothing changes.
same = tm.composite(img, mask, bgs, gen, 0.0)
check(bool(torch.equal(same, img)), "probability 0 leaves the photos as shot")
# Some photos get a visible shadow next to the rock.
ring = (torch.nn.functional.max_pool2d(disc[None, None], 31, 1, 15)[0, 0] > 0) & (disc == 0)
darkening = [float((b[:, ring] - out[i][:, ring]).mean()) for i in range(n)]
check(max(darkening) > 0.05, "a shadow is drawn next to the rock (largest mean darkening %.3f)" % max(darkening))

print("composite_test: %d failure(s)" % len(failures))
sys.exit(1 if failures else 0)
