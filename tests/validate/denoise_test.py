#!/usr/bin/python3
"""The Blender frames' denoiser (scripts/blender/denoise.py) on a synthetic
frame with known light: a disc with a soft shadow whose penumbra is as noisy
as Cycles' at 8 samples, a hard shadow edge with little noise, a stone of a
different normal and depth in front, and a grainy albedo everywhere.

Checks: the noise in the penumbra falls by at least 4x; the hard edge stays
within 2 px of its 10-90 % width; the albedo's grain comes through untouched
(the denoised light times the albedo, not a blur of the two); the stone's
light does not bleed onto the disc across the depth step; and the camera's
noise put in has the asked-for level at mid-grey.

Exit 77 (skip) without numpy.
"""

import os
import sys

try:
    import numpy as np
except ImportError:
    print("skip: numpy not installed (python3-numpy)")
    sys.exit(77)

sys.dont_write_bytecode = True  # leave the source tree as it was
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "scripts", "blender"))
import denoise  # noqa: E402

H, W = 160, 240
rng = np.random.default_rng(7)

# The scene's truth.
yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
light = np.ones((H, W), np.float32)
# Soft shadow: a 40 px penumbra ramp from 0.25 to 1 on the left half.
left = xx < 120
ramp = np.clip((xx - 20) / 40.0, 0, 1)
light = np.where(left & (yy > 20) & (yy < 140), 0.25 + 0.75 * ramp, light)
# Hard shadow edge (a low sun) on the right half: 0.3 below row 80.
right = xx >= 140
light = np.where(right & (yy >= 80), 0.3, light)
# The stone: a block in front (closer, facing the camera), lit at 0.6.
stone = (yy > 50) & (yy < 110) & (xx > 75) & (xx < 105)
light = np.where(stone, 0.6, light)
normal = np.zeros((H, W, 3), np.float32)
normal[..., 2] = 1.0
normal[stone] = (0.0, -1.0, 0.0)
depth = np.where(stone, 0.55, 0.7).astype(np.float32)
albedo = (0.55 + 0.3 * rng.random((H, W, 1))).astype(np.float32) * np.ones((1, 1, 3), np.float32)

# Relative noise of the light estimate per half render (4 samples): 35 % in
# the penumbra (a Bernoulli visibility), 2 % elsewhere.
penumbra = left & (yy > 20) & (yy < 140) & (ramp > 0) & (ramp < 1) & ~stone
rel = np.where(penumbra, 0.35 / np.sqrt(4), 0.02 / np.sqrt(4)).astype(np.float32)


def half_render():
    lt = light * (1 + rel * rng.standard_normal((H, W)).astype(np.float32))
    lt = np.maximum(lt, 0)[..., None] * np.ones((1, 1, 3), np.float32)
    zero = np.zeros((H, W, 3), np.float32)
    return {
        "Image": albedo * lt,
        "DiffDir": lt,
        "DiffInd": zero,
        "DiffCol": albedo,
        "GlossDir": zero,
        "GlossInd": zero,
        "GlossCol": zero,
        "Normal": normal,
        "Depth": np.repeat(depth[..., None], 3, axis=2),
    }


a, b = half_render(), half_render()
truth = albedo * light[..., None]
noisy = 0.5 * (a["Image"] + b["Image"])
# The filter alone first: no optics blur, no camera noise.
out = denoise.combine(a, b, 0.0, 0.0, rng, optics_blur_px=0.0)
failures = []


def rms(x, sel):
    return float(np.sqrt(np.mean(x[sel] ** 2)))


inner = penumbra.copy()
inner[:, :25] = False
e_noisy = rms((noisy - truth)[..., 1], inner)
e_out = rms((out - truth)[..., 1], inner)
print("penumbra: RMS error %.4f noisy, %.4f denoised (%.1fx)" % (e_noisy, e_out, e_noisy / e_out))
if e_out * 4 > e_noisy:
    failures.append("the penumbra's noise fell by %.1fx, not 4x" % (e_noisy / e_out))

# The hard edge: the light (out / albedo) across row 80, columns 150..230.
lt_out = (out / albedo)[..., 1]
col = lt_out[60:100, 150:230].mean(axis=1)
lo, hi = 0.3, 1.0
frac = (col - lo) / (hi - lo)
width = int(np.sum((frac > 0.1) & (frac < 0.9)))
print("hard edge: 10-90 %% width %d px" % width)
if width > 2:
    failures.append("the hard shadow edge is %d px wide (10-90 %%), more than 2" % width)

# The grain: out / truth has no albedo pattern left (correlation with albedo ~ 0).
ratio = (out / truth)[..., 1]
lit = (~penumbra) & (~stone) & (xx < 240) & (yy < 75) & right
c = np.corrcoef(ratio[lit], albedo[..., 1][lit])[0, 1]
print("grain: out/truth against albedo correlation %.3f on the lit disc" % c)
if abs(c) > 0.2:
    failures.append("the albedo's grain was smoothed with the light (correlation %.3f)" % c)

# No bleed across the stone's outline: the disc just left of the stone keeps its light.
ring = (~stone) & (xx >= 70) & (xx <= 75) & (yy > 55) & (yy < 105)
bleed = float(np.max(np.abs(lt_out[ring] - light[ring])))
print("stone outline: largest light error on the disc beside it %.3f" % bleed)
if bleed > 0.1:
    failures.append("the stone's light bled %.3f onto the disc beside it" % bleed)

# The optics blur (sigma 0.5 px, as the sim camera's): the mean is kept, and
# the albedo's pixel-to-pixel grain (white noise here) loses what a Gaussian of
# that width takes: the sum of its squared 2D weights (5x5 taps) is 0.41, so
# the standard deviation falls to 0.64.
blurred = denoise.combine(a, b, 0.0, 0.0, rng, optics_blur_px=0.5)
flat_lit = (yy > 5) & (yy < 15) & (xx > 5) & (xx < 235)
m0, m1 = float(out[..., 1][flat_lit].mean()), float(blurred[..., 1][flat_lit].mean())
s0, s1 = float(out[..., 1][flat_lit].std()), float(blurred[..., 1][flat_lit].std())
print("optics blur: mean %.4f -> %.4f, grain %.4f -> %.4f (x%.2f)" % (m0, m1, s0, s1, s1 / s0))
if abs(m1 - m0) > 0.01 * m0:
    failures.append("the optics blur changed the mean from %.4f to %.4f" % (m0, m1))
if not 0.58 < s1 / s0 < 0.70:
    failures.append("the optics blur left %.2f of the grain, not about 0.64" % (s1 / s0))

# The camera's noise: sigma_levels at mid-grey after the sRGB curve.
flat = {k: np.array(v) for k, v in half_render().items()}
for k in ("DiffDir", "Image"):
    flat[k] = np.full((H, W, 3), 0.2, np.float32) if k == "DiffDir" else np.full((H, W, 3), 0.2, np.float32)
flat["DiffCol"] = np.ones((H, W, 3), np.float32)
flat["Normal"] = normal * 0 + np.array((0, 0, 1), np.float32)
noisy_cam = denoise.combine(flat, flat, 2.0, 0.0, np.random.default_rng(3), optics_blur_px=0.0)


def srgb(x):
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 1e-9), 1 / 2.4) - 0.055)


levels = 255 * srgb(noisy_cam[..., 1])
s = float(np.std(levels))
print("camera noise at mid-grey: %.2f levels (asked 2.0)" % s)
if abs(s - 2.0) > 0.2:
    failures.append("the camera noise at mid-grey is %.2f levels, not 2.0" % s)

for f in failures:
    print("FAIL: " + f)
sys.exit(1 if failures else 0)
