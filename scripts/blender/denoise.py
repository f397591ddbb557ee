"""Takes the path tracer's noise out of a Cycles frame, and puts a camera's in.

At a few samples per pixel a path-traced frame is not what a camera sees:
where an area light is partly hidden (a soft shadow's penumbra) each sample
sees the light or not, and at 8 samples the estimate's relative noise there is
tens of percent, where a camera at base ISO has one or two. Blender's own
denoiser (OpenImageDenoise) is not in Debian's build, so this is the same idea
done here: the frame is rendered twice with independent sample seeds at half
the samples each; the lighting (Cycles' diffuse and glossy light passes, which
hold the light without the surfaces' colours) is smoothed by an edge-avoiding
a-trous wavelet filter whose weights come from the surface normals, the depth
and the lighting itself in units of its own noise (the two renders' difference
measures it pixel by pixel); the colours (the albedo passes: the stone's grain,
the pencil, the wood) are multiplied back untouched. A shadow's edge stays as
sharp as its noise lets it be seen; only where the light estimate is noisier
than the change across it is it smoothed.

Then the camera: shot noise and read noise in linear light, sigma^2 =
gain * x + read^2, scaled so that a mid-grey pixel (0.2 linear after the
exposure) gets `sigma_levels` 8-bit levels after the sRGB curve, as the sim
camera adds (config [sim] noise_sigma).

Run inside Blender's Python (numpy and bpy; see render_capture.py). The
numerical part needs numpy only (tests/validate/denoise_test.py).
"""

import math
import os

import numpy as np

# Cycles' render-layer outputs this needs, written to EXR per render.
PASSES = ("Image", "DiffDir", "DiffInd", "DiffCol", "GlossDir", "GlossInd", "GlossCol", "Normal", "Depth")


def add_pass_output(scene, tree, rl, tmp_dir):
    """Enables the passes and adds a File Output node writing each as a 32-bit
    EXR into tmp_dir (<pass>0001.exr for frame 1)."""
    vl = scene.view_layers[0]
    vl.use_pass_diffuse_direct = vl.use_pass_diffuse_indirect = vl.use_pass_diffuse_color = True
    vl.use_pass_glossy_direct = vl.use_pass_glossy_indirect = vl.use_pass_glossy_color = True
    vl.use_pass_normal = True
    vl.use_pass_z = True
    out = tree.nodes.new("CompositorNodeOutputFile")
    out.base_path = tmp_dir
    out.format.file_format = "OPEN_EXR"
    out.format.color_depth = "32"
    out.format.exr_codec = "NONE"
    out.format.color_mode = "RGB"
    out.file_slots.clear()
    for name in PASSES:
        out.file_slots.new(name)
        tree.links.new(rl.outputs[name], out.inputs[name])
    return out


def load_passes(tmp_dir, w, h):
    """The EXRs of the last render as float32 arrays (h, w, 3), top row first."""
    import bpy

    out = {}
    buf = np.empty(w * h * 4, np.float32)
    for name in PASSES:
        path = os.path.join(tmp_dir, name + "0001.exr")
        img = bpy.data.images.load(path)
        if tuple(img.size) != (w, h):
            raise RuntimeError("pass %s is %dx%d, not %dx%d" % (name, img.size[0], img.size[1], w, h))
        img.pixels.foreach_get(buf)
        bpy.data.images.remove(img)
        os.remove(path)
        out[name] = buf.reshape(h, w, 4)[::-1, :, :3].copy()
    return out


def _lum(x):
    return 0.2126 * x[..., 0] + 0.7152 * x[..., 1] + 0.0722 * x[..., 2]


def _box(x, r):
    """Mean over a (2r+1)^2 window, edges clamped."""
    p = np.pad(x, ((r, r), (r, r)), mode="edge")
    c = np.cumsum(np.cumsum(p, axis=0), axis=1)
    c = np.pad(c, ((1, 0), (1, 0)))
    k = 2 * r + 1
    return (c[k:, k:] - c[:-k, k:] - c[k:, :-k] + c[:-k, :-k]) / (k * k)


def atrous(signals, normal, depth, iterations=5, sigma_l=4.0, normal_power=64, depth_rel=0.01):
    """Edge-avoiding a-trous wavelet filter (3x3 B-spline taps, the step
    doubling each round) of each (sig (h, w, 3), var (h, w)) in `signals`,
    the variance carried through the rounds. Weights: normals
    (cos^normal_power, a power of 2), depth (relative difference over
    depth_rel), shared by the signals, and each signal's luminance in units of
    its own noise (sigma_l standard deviations). Returns the filtered signals."""
    h, w = normal.shape[:2]
    taps = ((-1, 0.25), (0, 0.5), (1, 0.25))
    squarings = max(0, int(round(np.log2(normal_power))))
    sigs = [s_.astype(np.float32) for s_, _ in signals]
    vars_ = [v_.astype(np.float32) for _, v_ in signals]
    for it in range(iterations):
        step = 1 << it
        pad = step

        def padded(x):
            widths = ((pad, pad), (pad, pad)) + (((0, 0),) if x.ndim == 3 else ())
            return np.pad(x, widths, mode="edge")

        npd, dp = padded(normal), padded(depth)
        sps = [padded(x) for x in sigs]
        vps = [padded(x) for x in vars_]
        lums = [_lum(x) for x in sigs]
        lps = [padded(x) for x in lums]
        # The luminance weight's scale: the noise, lightly smoothed (a one-pixel
        # variance estimate is itself noisy).
        sds = [(sigma_l * np.sqrt(np.maximum(_box(v, 1), 0.0)) + 1e-6).astype(np.float32) for v in vars_]
        inv_z = (1.0 / (depth_rel * depth + 1e-9)).astype(np.float32)
        accs = [np.zeros_like(x) for x in sigs]
        accws = [np.zeros((h, w), np.float32) for _ in sigs]
        accvs = [np.zeros((h, w), np.float32) for _ in sigs]
        for dy, ky in taps:
            for dx, kx in taps:
                ys, xs = pad + dy * step, pad + dx * step
                g = np.clip(np.einsum("ijk,ijk->ij", normal, npd[ys:ys + h, xs:xs + w]), 0.0, 1.0)
                for _ in range(squarings):
                    g *= g
                g *= np.float32(ky * kx) * np.exp(-np.abs(depth - dp[ys:ys + h, xs:xs + w]) * inv_z)
                for k in range(len(sigs)):
                    wgt = g * np.exp(-np.abs(lums[k] - lps[k][ys:ys + h, xs:xs + w]) / sds[k])
                    accs[k] += wgt[..., None] * sps[k][ys:ys + h, xs:xs + w]
                    accws[k] += wgt
                    accvs[k] += wgt * wgt * vps[k][ys:ys + h, xs:xs + w]
        for k in range(len(sigs)):
            aw = np.maximum(accws[k], 1e-12)
            sigs[k] = accs[k] / aw[..., None]
            vars_[k] = accvs[k] / (aw * aw)
    return sigs


def _gauss(x, sigma):
    """Separable Gaussian blur of (h, w, c), edges clamped."""
    r = max(1, int(math.ceil(3 * sigma)))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2).astype(np.float32)
    k /= k.sum()
    p = np.pad(x, ((r, r), (0, 0), (0, 0)), mode="edge")
    y = sum(k[i] * p[i:i + x.shape[0]] for i in range(2 * r + 1))
    p = np.pad(y, ((0, 0), (r, r), (0, 0)), mode="edge")
    return sum(k[i] * p[:, i:i + x.shape[1]] for i in range(2 * r + 1))


def combine(a, b, camera_sigma_levels, exposure_ev, rng, optics_blur_px=0.5):
    """The denoised frame (linear, before the exposure) from two renders' passes.
    optics_blur_px: the lens and sensor blur (Gaussian sigma, px) the sim camera
    applies too; it also takes out the aliasing of a texture sampled at a few
    points per pixel, which the albedo passes keep."""
    avg = {k: 0.5 * (a[k] + b[k]) for k in PASSES}
    normal = avg["Normal"]
    nn = np.linalg.norm(normal, axis=2, keepdims=True)
    normal = np.where(nn > 1e-6, normal / np.maximum(nn, 1e-6), 0.0)
    depth = np.minimum(avg["Depth"][..., 0], 1e6)
    out = avg["Image"].copy()
    signals, colours = [], []
    for light, colour in (("Diff", "DiffCol"), ("Gloss", "GlossCol")):
        la = a[light + "Dir"] + a[light + "Ind"]
        lb = b[light + "Dir"] + b[light + "Ind"]
        # Variance of the two renders' mean from their difference.
        var = _box(0.25 * (_lum(la) - _lum(lb)) ** 2, 2)
        signals.append((0.5 * (la + lb), var))
        colours.append(avg[colour])
    for (mean, _), smooth, colour in zip(signals, atrous(signals, normal, depth), colours):
        out += colour * (smooth - mean)
    out = np.maximum(out, 0.0)
    if optics_blur_px > 0:
        out = _gauss(out, optics_blur_px)
    if camera_sigma_levels > 0:
        # sigma^2 = g x + r^2 in exposed linear units; at x = 0.2 the sRGB
        # curve's slope is 1.124, so sigma_levels/255/1.124 there.
        k = 2.0 ** exposure_ev
        x = out * k
        s02 = camera_sigma_levels / 255.0 / 1.124
        read = 0.25 * s02
        gain = (s02 * s02 - read * read) / 0.2
        sigma = np.sqrt(gain * np.maximum(x, 0.0) + read * read)
        out = np.maximum(x + sigma * rng.standard_normal(x.shape).astype(np.float32), 0.0) / k
    return out


def save_png(scene, lin, path):
    """Writes linear RGB (h, w, 3), top row first, through the scene's colour
    management (exposure, view transform, dither) as its render output."""
    import bpy

    h, w = lin.shape[:2]
    img = bpy.data.images.new("aggscan-denoised", w, h, alpha=False, float_buffer=True)
    rgba = np.ones((h, w, 4), np.float32)
    rgba[..., :3] = lin[::-1]
    img.pixels.foreach_set(rgba.ravel())
    img.save_render(path, scene=scene)
    bpy.data.images.remove(img)
