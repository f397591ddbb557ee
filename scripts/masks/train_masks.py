#!/usr/bin/python3
"""Trains the rig's salient-object mask network on CPU and exports it to ONNX.

Input: a dataset written by `aggscan masks dataset` (index.json listing
pairs of a photo and the silhouette of the rig's own reconstructed mesh
projected into it, PNG 0/255). Output: an ONNX model that the worker runs
through OpenCV DNN (pipeline/masks/mask_net.h: 1x3xHxW RGB input normalised with
ImageNet's mean/std, one 1x1xhxw probability map), and MODEL.json with
what was trained and how long it took.

The network is a small U-Net (about 0.3 M parameters) built only from ops
that Debian 12's OpenCV 4.6 DNN reads: Conv (BatchNorm folded into it at
export), Relu, MaxPool, Resize (nearest), Concat, Sigmoid.

Run with Debian's python (/usr/bin/python3): python3-torch and
python3-opencv. Deterministic for a given seed and thread count.
"""

import argparse
import json
import math
import os
import sys
import time

EXIT_USAGE = 2
EXIT_MISSING = 3  # a Python module is missing: the message names the package


def fail(code, msg):
    print("train_masks: " + msg, file=sys.stderr)
    sys.exit(code)


try:
    import numpy as np
    import torch
    import torch.nn as nn
    import torch.nn.functional as F
except ImportError as e:
    fail(EXIT_MISSING, "cannot import %s (%s): install Debian's python3-torch "
         "(apt-get install python3-torch) and run this script with /usr/bin/python3" % (e.name, e))
try:
    import cv2
except ImportError as e:
    fail(EXIT_MISSING, "cannot import cv2 (%s): install Debian's python3-opencv "
         "(apt-get install python3-opencv)" % e)

# The normalisation MaskNet applies (config [mask] mean_* / std_*: ImageNet's).
MEAN_RGB = (0.485, 0.456, 0.406)
STD_RGB = (0.229, 0.224, 0.225)


def conv_bn_relu(cin, cout):
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout),
                         nn.ReLU(inplace=True))


class Block(nn.Sequential):
    def __init__(self, cin, cout):
        super().__init__(conv_bn_relu(cin, cout), conv_bn_relu(cout, cout))


class Up(nn.Module):
    """Nearest x2 upsampling of the coarser map (reduced by a 1x1 conv first,
    which is cheaper than convolving it at the finer size), concatenated with
    the skip connection, then one 3x3 conv."""

    def __init__(self, cin, cskip, cout):
        super().__init__()
        self.reduce = nn.Sequential(nn.Conv2d(cin, cskip, 1, bias=False), nn.BatchNorm2d(cskip),
                                    nn.ReLU(inplace=True))
        self.up = nn.Upsample(scale_factor=2, mode="nearest")
        self.fuse = conv_bn_relu(2 * cskip, cout)

    def forward(self, x, skip):
        return self.fuse(torch.cat([self.up(self.reduce(x)), skip], dim=1))


class MaskUNet(nn.Module):
    """Encoder-decoder with skip connections. The stem convolves with stride
    2 and the map comes out at half the input size: the full-resolution level
    cost most of the time on the rig's CPU, and the worker resizes the map to
    the photo and refines its boundary there anyway (RefineForegroundMask)."""

    def __init__(self, widths=(12, 24, 48, 96)):
        super().__init__()
        w = widths
        self.stem = nn.Sequential(nn.Conv2d(3, w[0], 3, stride=2, padding=1, bias=False), nn.BatchNorm2d(w[0]),
                                  nn.ReLU(inplace=True), conv_bn_relu(w[0], w[0]))
        self.enc = nn.ModuleList([Block(w[i - 1], w[i]) for i in range(1, len(w))])
        self.pool = nn.MaxPool2d(2)
        self.dec = nn.ModuleList([Up(w[i + 1], w[i], w[i]) for i in reversed(range(len(w) - 1))])
        self.head = nn.Conv2d(w[0], 1, 1)

    def forward(self, x):
        x = self.stem(x)
        skips = [x]
        for e in self.enc:
            x = e(self.pool(x))
            skips.append(x)
        x = skips.pop()
        for d in self.dec:
            x = d(x, skips.pop())
        return self.head(x)  # logits at half the input size; the exported model ends in a Sigmoid


class Exported(nn.Module):
    def __init__(self, net):
        super().__init__()
        self.net = net

    def forward(self, x):
        return torch.sigmoid(self.net(x))


def load_dataset(root, width, height, margin):
    """Every pair of index.json, resized to margin x the input size (room for
    the zoom-in augmentation): uint8 images N x 3 x H x W (RGB) and float
    masks N x 1 x H x W in 0..1."""
    index_path = os.path.join(root, "index.json")
    if not os.path.isfile(index_path):
        fail(EXIT_USAGE, "%s not found: make the dataset first with `aggscan masks dataset --out %s "
             "SAMPLE_DIR...`" % (index_path, root))
    try:
        with open(index_path) as f:
            index = json.load(f)
        pairs = index["pairs"]
    except (ValueError, KeyError, TypeError) as e:
        fail(EXIT_USAGE, "%s is not a mask dataset index (%s): make it again with `aggscan masks dataset`"
             % (index_path, e))
    if not pairs:
        fail(EXIT_USAGE, "%s lists no image-mask pairs" % index_path)
    W, H = int(round(width * margin)), int(round(height * margin))
    imgs = np.zeros((len(pairs), 3, H, W), np.uint8)
    masks = np.zeros((len(pairs), 1, H, W), np.float32)
    for i, p in enumerate(pairs):
        ip, mp = os.path.join(root, p["image"]), os.path.join(root, p["mask"])
        img = cv2.imread(ip, cv2.IMREAD_COLOR)
        m = cv2.imread(mp, cv2.IMREAD_GRAYSCALE)
        if img is None:
            fail(EXIT_USAGE, "cannot read the photo %s listed in %s" % (ip, index_path))
        if m is None:
            fail(EXIT_USAGE, "cannot read the mask %s listed in %s" % (mp, index_path))
        if img.shape[:2] != m.shape[:2]:
            fail(EXIT_USAGE, "%s is %dx%d but its mask %s is %dx%d" % (ip, img.shape[1], img.shape[0], mp,
                                                                     m.shape[1], m.shape[0]))
        img = cv2.cvtColor(cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2RGB)
        imgs[i] = img.transpose(2, 0, 1)
        masks[i, 0] = cv2.resize((m > 127).astype(np.float32), (W, H), interpolation=cv2.INTER_AREA)
    return torch.from_numpy(imgs), torch.from_numpy(masks), pairs


def load_backgrounds(dirs, width, height, margin):
    """Every photo under the given folders (the environment's empty turntable:
    the disc, the floor and the lights of the place the rig works in, no
    rock), resized like the dataset's photos: uint8 N x 3 x H x W (RGB)."""
    files = []
    for d in dirs:
        if not os.path.isdir(d):
            fail(EXIT_USAGE, "--backgrounds %s is not a folder" % d)
        for root, _, names in os.walk(d):
            files += [os.path.join(root, f) for f in sorted(names)
                      if f.lower().endswith((".jpg", ".jpeg", ".png"))]
    if not files:
        fail(EXIT_USAGE, "--backgrounds %s holds no .jpg or .png photos of the empty turntable"
             % " ".join(dirs))
    W, H = int(round(width * margin)), int(round(height * margin))
    out = np.zeros((len(files), 3, H, W), np.uint8)
    for i, f in enumerate(sorted(files)):
        img = cv2.imread(f, cv2.IMREAD_COLOR)
        if img is None:
            fail(EXIT_USAGE, "cannot read the background photo %s" % f)
        out[i] = cv2.cvtColor(cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA),
                              cv2.COLOR_BGR2RGB).transpose(2, 0, 1)
    return torch.from_numpy(out), files


def blur(m, sigma):
    """Separable Gaussian blur of N x 1 x H x W maps, one sigma (px) per map."""
    out = torch.empty_like(m)
    for i in range(m.shape[0]):
        s = float(sigma[i])
        x = m[i:i + 1]
        f = max(1, int(s / 2))  # wide blurs at reduced size: the result is smooth anyway
        if f > 1:
            x = F.avg_pool2d(x, f, f, ceil_mode=True)
            s /= f
        r = max(1, int(math.ceil(3 * s)))
        t = torch.arange(-r, r + 1, dtype=torch.float32)
        k = torch.exp(-0.5 * (t / s) ** 2)
        k = k / k.sum()
        x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
        x = F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))
        if f > 1:
            x = F.interpolate(x, size=m.shape[-2:], mode="bilinear", align_corners=False)
        out[i:i + 1] = x
    return out


def composite(img, mask, bgs, gen, p):
    """The rig's own rocks (the pixels inside their reconstructed silhouette)
    laid onto the new environment's empty-turntable photos, each with a cast
    shadow drawn in (its silhouette shifted away from a random light, softened
    and darkened by a random amount, plus a contact shadow where it stands and
    the dark ground under its overhang), and
    its colour changed at random (a darker or yellower stone than the rig has
    seen). With probability p per photo; img is float 0..1, N x 3 x H x W."""
    n, _, H, W = img.shape
    pick = torch.rand(n, generator=gen) < p
    if not bool(pick.any()):
        return img
    idx = torch.nonzero(pick).flatten()
    k = idx.numel()
    r = lambda lo, hi: torch.rand(k, generator=gen) * (hi - lo) + lo
    bg = bgs[torch.randint(0, bgs.shape[0], (k,), generator=gen)].float() / 255.0
    m = mask[idx]
    size = m.sum(dim=(1, 2, 3)).clamp(min=1).sqrt()  # the rock's size in px
    # Cast shadow: the silhouette moved away from the light and softened.
    ang = r(0, 2 * math.pi)
    length = r(0.0, 0.6) * size
    theta = torch.zeros(k, 2, 3)
    theta[:, 0, 0] = 1
    theta[:, 1, 1] = 1
    theta[:, 0, 2] = -2 * length * torch.cos(ang) / W
    theta[:, 1, 2] = -2 * length * torch.sin(ang) / H
    grid = F.affine_grid(theta, (k, 1, H, W), align_corners=False)
    cast = F.grid_sample(m, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    cast = blur(torch.maximum(cast, m), r(0.5, 0.12 * float(size.mean()) + 1))
    contact = blur(F.max_pool2d(m, 5, 1, 2), r(1.0, 4.0))
    # Under the rock's overhang the camera, looking down at the disc, sees the
    # ground the rock hides from every light: a nearly black band along the
    # bottom of the silhouette (image y grows towards the camera).
    theta[:, 0, 2] = 0
    theta[:, 1, 2] = -2 * r(0.02, 0.12) * size / H
    grid = F.affine_grid(theta, (k, 1, H, W), align_corners=False)
    under = blur(F.grid_sample(m, grid, mode="bilinear", padding_mode="zeros", align_corners=False),
                 r(0.7, 3.0))
    shade = torch.maximum(cast * r(0.0, 0.8).view(k, 1, 1, 1), contact * r(0.2, 0.9).view(k, 1, 1, 1))
    shade = torch.maximum(shade, under * r(0.3, 0.95).view(k, 1, 1, 1))
    bg = bg * (1 - shade)
    # Another stone: its grain's contrast (a smooth dolomite .. a speckled
    # granite), a tint of any hue and up to the saturation of a yellowish
    # dolomite or a reddish sandstone, and an overall gain (dark basalt ..
    # pale limestone).
    rock = img[idx]
    lum = (0.299 * rock[:, 0:1] + 0.587 * rock[:, 1:2] + 0.114 * rock[:, 2:3])
    mean = (lum * m).sum(dim=(2, 3), keepdim=True) / m.sum(dim=(2, 3), keepdim=True).clamp(min=1)
    lum = mean + (lum - mean) * r(0.4, 1.2).view(k, 1, 1, 1)
    hue = r(0, 2 * math.pi).view(k, 1)
    sat = r(0, 0.5).view(k, 1)
    phase = torch.tensor([0.0, 2 * math.pi / 3, 4 * math.pi / 3]).view(1, 3)
    tint = 1 + sat * torch.cos(hue - phase)  # mean 1 over the three channels
    keep = r(0, 1).view(k, 1, 1, 1)  # how much of the rig's own colour stays
    rock = keep * rock + (1 - keep) * lum * tint.view(k, 3, 1, 1)
    rock = rock * r(0.25, 1.2).view(k, 1, 1, 1)
    # The mask, resized with area averaging, is already the edge's coverage;
    # widening it would bring the old disc's colour in as a halo.
    alpha = m
    out = img.clone()
    out[idx] = (alpha * rock + (1 - alpha) * bg).clamp(0, 1)
    return out


def augment(img, mask, out_hw, gen, margin):
    """A batch's geometric (scale, shift, flips) and photometric (brightness,
    contrast, saturation, white balance, gamma) augmentation of float 0..1
    photos; returns the normalised input and the mask at out_hw."""
    n = img.shape[0]
    r = lambda lo, hi: torch.rand(n, generator=gen) * (hi - lo) + lo
    # Geometry: the source holds margin x the view; s < 1 zooms in, > 1 out.
    s = r(0.8, 1.35) / margin
    tx, ty = r(-0.15, 0.15), r(-0.15, 0.15)
    fx = torch.where(torch.rand(n, generator=gen) < 0.5, -1.0, 1.0)
    fy = torch.where(torch.rand(n, generator=gen) < 0.2, -1.0, 1.0)
    theta = torch.zeros(n, 2, 3)
    theta[:, 0, 0] = s * fx
    theta[:, 1, 1] = s * fy
    theta[:, 0, 2] = tx
    theta[:, 1, 2] = ty
    grid = F.affine_grid(theta, (n, 3) + tuple(out_hw), align_corners=False)
    x = F.grid_sample(img, grid, mode="bilinear", padding_mode="reflection",
                      align_corners=False)
    y = F.grid_sample(mask, grid, mode="bilinear", padding_mode="reflection", align_corners=False)
    # Colour: rigs differ in exposure, white balance and the stones' colour.
    b = r(0.6, 1.4).view(n, 1, 1, 1)
    c = r(0.7, 1.3).view(n, 1, 1, 1)
    sat = r(0.5, 1.5).view(n, 1, 1, 1)
    wb = (torch.rand(n, 3, generator=gen) * 0.2 + 0.9).view(n, 3, 1, 1)
    gamma = r(0.75, 1.33).view(n, 1, 1, 1)
    gray = (0.299 * x[:, 0:1] + 0.587 * x[:, 1:2] + 0.114 * x[:, 2:3])
    x = gray + (x - gray) * sat
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    x = (x - mean) * c + mean
    x = (x * b * wb).clamp(0, 1) ** gamma
    x = x + torch.randn(x.shape, generator=gen) * 0.01
    m = torch.tensor(MEAN_RGB).view(1, 3, 1, 1)
    sd = torch.tensor(STD_RGB).view(1, 3, 1, 1)
    return (x - m) / sd, y


def plain_input(img_u8, out_hw):
    x = F.interpolate(img_u8.float() / 255.0, size=tuple(out_hw), mode="area")
    m = torch.tensor(MEAN_RGB).view(1, 3, 1, 1)
    sd = torch.tensor(STD_RGB).view(1, 3, 1, 1)
    return (x - m) / sd


def loss_fn(logits, target):
    """Binary cross-entropy plus soft Dice: the Dice term keeps a small rock
    from being outweighed by the background."""
    if target.shape[-2:] != logits.shape[-2:]:
        target = F.adaptive_avg_pool2d(target, logits.shape[-2:])
    bce = F.binary_cross_entropy_with_logits(logits, target)
    p = torch.sigmoid(logits)
    inter = (p * target).sum(dim=(1, 2, 3))
    dice = 1 - (2 * inter + 1) / (p.sum(dim=(1, 2, 3)) + target.sum(dim=(1, 2, 3)) + 1)
    return bce + dice.mean()


def check_with_opencv(path, exported, sample, out_hw):
    """The exported file loads in OpenCV DNN and gives what torch gives (in
    eval mode: export restores the mode the module had)."""
    dnn = cv2.dnn.readNetFromONNX(path)
    dnn.setPreferableBackend(cv2.dnn.DNN_BACKEND_OPENCV)
    dnn.setPreferableTarget(cv2.dnn.DNN_TARGET_CPU)
    dnn.setInput(sample.numpy())
    got = dnn.forward()
    exported.eval()
    with torch.no_grad():
        want = exported(sample).numpy()
    if got.size != want.size:
        raise RuntimeError("OpenCV DNN gives an output of shape %s, torch %s" % (got.shape, want.shape))
    return float(np.abs(got.reshape(want.shape) - want).max())


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", required=True, help="directory written by `aggscan masks dataset`")
    ap.add_argument("--out", required=True, help="the .onnx file to write")
    ap.add_argument("--epochs", type=int, default=30)
    ap.add_argument("--width", type=int, default=320, help="network input width (mask.input_width)")
    ap.add_argument("--height", type=int, default=320, help="network input height (mask.input_height)")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--lr", type=float, default=3e-3)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--threads", type=int, default=2, help="CPU threads (the rig has 2 cores)")
    ap.add_argument("--backgrounds", nargs="+", default=[],
                    help="folders of empty-turntable photos of the environment to teach: the dataset's "
                         "rocks are composited onto them (with drawn shadows) as well as seen as shot")
    ap.add_argument("--composite", type=float, default=0.7,
                    help="share of the training photos composited onto --backgrounds")
    a = ap.parse_args()
    if a.epochs < 1 or a.width < 32 or a.height < 32 or a.width % 16 or a.height % 16 or a.batch < 1:
        fail(EXIT_USAGE, "--epochs and --batch must be >= 1, --width and --height multiples of 16 (the "
             "network halves its maps 4 times) and at least 32")
    out_dir = os.path.dirname(os.path.abspath(a.out))
    if not os.path.isdir(out_dir):
        fail(EXIT_USAGE, "the directory of --out (%s) does not exist" % out_dir)

    torch.set_num_threads(a.threads)
    torch.manual_seed(a.seed)
    np.random.seed(a.seed)
    torch.use_deterministic_algorithms(True)
    gen = torch.Generator().manual_seed(a.seed)

    t0 = time.monotonic()
    margin = 1.25
    imgs, masks, pairs = load_dataset(a.dataset, a.width, a.height, margin)
    bgs, bg_files = (load_backgrounds(a.backgrounds, a.width, a.height, margin) if a.backgrounds
                     else (None, []))
    t_load = time.monotonic() - t0
    n = imgs.shape[0]
    out_hw = (a.height, a.width)
    net = MaskUNet()
    params = sum(p.numel() for p in net.parameters())
    print("train_masks: %d pairs from %s, %d background photos, %d parameters, input %dx%d, %d epochs, "
          "%d threads" % (n, a.dataset, len(bg_files), params, a.width, a.height, a.epochs, a.threads),
          flush=True)
    opt = torch.optim.AdamW(net.parameters(), lr=a.lr, weight_decay=1e-4)
    steps_per_epoch = max(1, math.ceil(n / a.batch))
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=a.lr, total_steps=a.epochs * steps_per_epoch,
                                                pct_start=0.15)
    history = []
    t_train = time.monotonic()
    for epoch in range(a.epochs):
        net.train()
        order = torch.randperm(n, generator=gen)
        total, seen = 0.0, 0
        for k in range(0, n, a.batch):
            idx = order[k:k + a.batch]
            if idx.numel() < 2 and n >= 2:
                continue  # BatchNorm needs more than one sample
            x = imgs[idx].float() / 255.0
            if bgs is not None:
                x = composite(x, masks[idx], bgs, gen, a.composite)
            x, y = augment(x, masks[idx], out_hw, gen, margin)
            loss = loss_fn(net(x), y)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += float(loss) * idx.numel()
            seen += idx.numel()
        # IoU of the network alone on the training pairs, unaugmented: a
        # progress figure, not a held-out score (aggscan masks eval is that).
        net.eval()
        inter = union = 0.0
        with torch.no_grad():
            for k in range(0, n, 16):
                p = torch.sigmoid(net(plain_input(imgs[k:k + 16], out_hw))) > 0.5
                t = F.interpolate(masks[k:k + 16], size=tuple(p.shape[-2:]), mode="area") > 0.5
                inter += float((p & t).sum())
                union += float((p | t).sum())
        iou = inter / union if union else 0.0
        history.append({"epoch": epoch + 1, "loss": total / max(1, seen), "train_iou": iou,
                        "seconds": time.monotonic() - t_train})
        print("train_masks: epoch %d/%d loss %.4f train IoU %.4f (%.0f s)"
              % (epoch + 1, a.epochs, total / max(1, seen), iou, time.monotonic() - t_train), flush=True)
    train_s = time.monotonic() - t_train

    exported = Exported(net).eval()
    dummy = torch.zeros(1, 3, a.height, a.width)
    tmp = a.out + ".tmp"
    torch.onnx.export(exported, dummy, tmp, opset_version=11, input_names=["image"],
                      output_names=["probability"], do_constant_folding=True,
                      training=torch.onnx.TrainingMode.EVAL)
    try:
        diff = check_with_opencv(tmp, exported, plain_input(imgs[:1], out_hw), out_hw)
    except Exception as e:  # cv2.error or a shape mismatch: the file is not usable by the worker
        os.unlink(tmp)
        fail(1, "the exported model does not run in OpenCV DNN %s: %s" % (cv2.__version__, e))
    if diff > 1e-3:
        os.unlink(tmp)
        fail(1, "OpenCV DNN's output differs from torch's by %.3g: the export is not faithful" % diff)
    os.replace(tmp, a.out)
    report = {
        "model": os.path.abspath(a.out),
        "dataset": os.path.abspath(a.dataset),
        "pairs": n,
        "samples": sorted({p.get("sample", "") for p in pairs}),
        "backgrounds": [os.path.abspath(d) for d in a.backgrounds],
        "background_photos": len(bg_files),
        "composite_share": a.composite if bg_files else 0.0,
        "parameters": params,
        "model_bytes": os.path.getsize(a.out),
        "input_width": a.width, "input_height": a.height,
        "mean_rgb": MEAN_RGB, "std_rgb": STD_RGB, "output": "probability",
        "epochs": a.epochs, "batch": a.batch, "lr": a.lr, "seed": a.seed, "threads": a.threads,
        "torch": torch.__version__, "opencv": cv2.__version__,
        "load_seconds": t_load, "train_seconds": train_s,
        "opencv_vs_torch_max_abs_diff": diff,
        "history": history,
    }
    with open(a.out + ".json.tmp", "w") as f:
        json.dump(report, f, indent=1)
    os.replace(a.out + ".json.tmp", a.out + ".json")
    print("train_masks: wrote %s (%d bytes), trained in %.0f s; OpenCV DNN matches torch within %.2g"
          % (a.out, report["model_bytes"], train_s, diff), flush=True)


if __name__ == "__main__":
    main()
