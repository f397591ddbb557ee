"""The reports' figures, drawn with matplotlib (Agg, no display): the study's
Figures 6, 7 and 8, the gradation curve, the distributions, each rock's
photos with its mask outline, and its mesh from three directions.

Every function returns a matplotlib Figure; report.py turns it into SVG (the
plots: text stays text in the PDF) or PNG (photos, renderings).
"""

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402

SIDE_COLOURS = {1: "#1f77b4", 2: "#d62728", 3: "#2ca02c", 4: "#9467bd"}


def _fig(w=6.4, h=3.6, rows=1, cols=1, **kw):
    fig, axes = plt.subplots(rows, cols, figsize=(w, h), **kw)
    return fig, axes


# --- one rock ---------------------------------------------------------------


def rock_figure7(views, fer_3d, sphericity):
    """Each view's 2D FER and circularity against the rock's 3D FER and
    sphericity (the study's Figure 7 for one rock)."""
    fig, (ax1, ax2) = _fig(6.4, 4.8, 2, 1, sharex=True)
    for side in sorted({v["side"] for v in views}):
        vs = [v for v in views if v["side"] == side]
        x = [v["angle_deg"] % 360.0 if isinstance(v.get("angle_deg"), (int, float))
             else v["view"] for v in vs]
        ax1.plot(x, [v["fer_2d"] for v in vs], "o", ms=4, color=SIDE_COLOURS.get(side, "k"),
                 label=f"side {side}, 2D FER")
        ax2.plot(x, [v["circularity"] for v in vs], "o", ms=4, color=SIDE_COLOURS.get(side, "k"),
                 label=f"side {side}, circularity")
    ax1.axhline(fer_3d, color="k", lw=1.5, label=f"3D FER {fer_3d:.3f}")
    ax2.axhline(sphericity, color="k", lw=1.5, label=f"sphericity {sphericity:.3f}")
    ax1.set_ylabel("FER")
    ax2.set_ylabel("circularity / sphericity")
    ax2.set_xlabel("turntable angle of the view (deg)")
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    return fig


def rock_figure8(fer_2d, ratio_c_b, ratio_b_a):
    """The mean 2D FER (min-max bar) against the rock's c/b and b/a (the
    study's Figure 8 for one rock)."""
    fig, ax = _fig(6.4, 2.6)
    ax.errorbar([fer_2d["mean"]], [0], xerr=[[fer_2d["mean"] - fer_2d["min"]],
                                             [fer_2d["max"] - fer_2d["mean"]]],
                fmt="o", color="k", capsize=4, label="2D FER, mean (min-max of the views)")
    ax.plot([ratio_c_b], [0], "s", color="#1f77b4", ms=8, label=f"c/b {ratio_c_b:.3f}")
    ax.plot([ratio_b_a], [0], "^", color="#d62728", ms=8, label=f"b/a {ratio_b_a:.3f}")
    ax.set_yticks([])
    ax.set_xlabel("ratio")
    ax.grid(alpha=0.3, axis="x")
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    return fig


def photo_with_outline(image_path, mask_path, title):
    """A stored view with the worker's mask outline drawn on it."""
    img = plt.imread(image_path)
    mask = None
    if mask_path:
        mask = plt.imread(mask_path)
        if mask.ndim == 3:
            mask = mask[..., 0]
        if mask.shape[:2] != img.shape[:2]:
            mask = None
    # The rock and a margin of half its size around it: it fills a small
    # part of the frame.
    if mask is not None and mask.max() > 0:
        ys, xs = np.nonzero(mask > 0.5 * float(mask.max()))
        h, w = ys.max() - ys.min() + 1, xs.max() - xs.min() + 1
        side = int(max(h, w) * 1.6)
        cy, cx = (ys.max() + ys.min()) // 2, (xs.max() + xs.min()) // 2
        y0 = max(0, min(img.shape[0] - side, cy - side // 2))
        x0 = max(0, min(img.shape[1] - side, cx - side // 2))
        img = img[y0:y0 + side, x0:x0 + side]
        mask = mask[y0:y0 + side, x0:x0 + side]
    step = max(1, img.shape[1] // 480)  # a report needs no more than ~480 px
    img = img[::step, ::step]
    fig, ax = _fig(3.2, 3.2 * img.shape[0] / img.shape[1])
    ax.imshow(img)
    if mask is not None:
        mask = mask[::step, ::step]
        ax.contour(mask, levels=[0.5 * float(mask.max() or 1)], colors=["#ffd500"],
                   linewidths=1.2)
    ax.set_title(title, fontsize=8)
    ax.axis("off")
    fig.subplots_adjust(0, 0, 1, 0.92)
    return fig


def read_ply(path):
    """Vertices (n x 3, mm), their colours (n x 3, 0-1 or None) and
    triangles (m x 3) of a PLY file as the worker writes it (binary little
    endian or ASCII; doubles or floats; uchar colours)."""
    with open(path, "rb") as f:
        header = []
        while True:
            line = f.readline()
            if not line:
                raise ValueError(f"{path}: the PLY header has no end_header")
            line = line.decode("ascii", "replace").strip()
            header.append(line)
            if line == "end_header":
                break
        body = f.read()
    fmt = next((h.split()[1] for h in header if h.startswith("format ")), "")
    elements, current = [], None
    for h in header:
        p = h.split()
        if p[0] == "element":
            current = {"name": p[1], "count": int(p[2]), "props": []}
            elements.append(current)
        elif p[0] == "property" and current is not None:
            current["props"].append(p[1:])
    types = {"double": "d", "float": "f", "uchar": "B", "int": "i", "uint": "I", "float32": "f",
             "float64": "d", "uint8": "B", "int32": "i", "uint32": "I", "short": "h",
             "ushort": "H", "char": "b"}
    verts = cols = faces = None
    if fmt == "ascii":
        tokens = body.split()
        pos = 0
        for el in elements:
            if el["name"] == "vertex":
                k = len(el["props"])
                arr = np.array(tokens[pos:pos + k * el["count"]], dtype=float).reshape(-1, k)
                pos += k * el["count"]
                names = [p[-1] for p in el["props"]]
                verts = arr[:, [names.index(c) for c in "xyz"]]
                if "red" in names:
                    cols = arr[:, [names.index(c) for c in ("red", "green", "blue")]] / 255.0
            elif el["name"] == "face":
                fl = []
                for _ in range(el["count"]):
                    n = int(tokens[pos])
                    fl.append([int(t) for t in tokens[pos + 1:pos + 1 + n]][:3])
                    pos += 1 + n
                faces = np.array(fl, dtype=np.int64)
    else:
        if fmt != "binary_little_endian":
            raise ValueError(f"{path}: PLY format {fmt!r} is not read here")
        pos = 0
        for el in elements:
            if el["name"] == "vertex":
                dt = np.dtype([(p[-1], "<" + types[p[0]]) for p in el["props"]])
                arr = np.frombuffer(body, dtype=dt, count=el["count"], offset=pos)
                pos += dt.itemsize * el["count"]
                verts = np.stack([arr[c].astype(float) for c in "xyz"], axis=1)
                if "red" in dt.names:
                    cols = np.stack([arr[c] for c in ("red", "green", "blue")], axis=1) / 255.0
            elif el["name"] == "face":
                cnt_t, idx_t = types[el["props"][0][1]], types[el["props"][0][2]]
                # Triangles throughout (the worker writes nothing else):
                # read as fixed records, checked.
                dt = np.dtype([("n", "<" + cnt_t), ("i", "<" + idx_t, (3,))])
                arr = np.frombuffer(body, dtype=dt, count=el["count"], offset=pos)
                if not np.all(arr["n"] == 3):
                    raise ValueError(f"{path}: faces other than triangles")
                faces = arr["i"].astype(np.int64)
                pos += dt.itemsize * el["count"]
    if verts is None or faces is None:
        raise ValueError(f"{path}: no vertices or faces")
    return verts, cols, faces


def mesh_views(path, title=""):
    """The mesh from above, the front and the side, orthographic, shaded by a
    light over the viewer's shoulder and coloured with its vertex colours."""
    verts, cols, faces = read_ply(path)
    centre = verts.mean(axis=0)
    v = verts - centre
    # The three directions along the mesh's own principal axes: longest
    # horizontal, so each view shows the rock as a person would lay it.
    _, _, axes = np.linalg.svd(v - v.mean(axis=0), full_matrices=False)
    v = v @ axes.T
    tri = v[faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True) + 1e-12
    base = cols[faces].mean(axis=1) if cols is not None else np.full((len(faces), 3), 0.7)
    extent = np.abs(v).max() * 1.08
    fig, axs = _fig(7.2, 2.6, 1, 3)
    for ax, (name, view_axis, right, up) in zip(
            axs, [("top (a-b plane)", 2, 0, 1), ("front (a-c plane)", 1, 0, 2),
                  ("side (b-c plane)", 0, 1, 2)]):
        facing = normals[:, view_axis] > 0
        light = np.array([0.0, 0.0, 0.0])
        light[view_axis], light[right], light[up] = 0.8, -0.35, 0.45
        light /= np.linalg.norm(light)
        shade = np.clip(normals @ light, 0, 1) * 0.75 + 0.25
        colours = np.clip(base * shade[:, None], 0, 1)
        order = np.argsort(tri[:, :, view_axis].mean(axis=1))
        order = order[facing[order]]
        polys = tri[order][:, :, [right, up]]
        ax.add_collection(PolyCollection(polys, facecolors=colours[order], edgecolors="none",
                                         antialiaseds=False))
        ax.set_xlim(-extent, extent)
        ax.set_ylim(-extent, extent)
        ax.set_aspect("equal")
        ax.set_title(name, fontsize=8)
        ax.tick_params(labelsize=6)
        ax.set_xlabel("mm", fontsize=6)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return fig


# --- a batch ------------------------------------------------------------------


def batch_figure6(ids, measured_cm3, reference_cm3, mpe, mape):
    """Reconstructed against reference volume (the study's Figure 6)."""
    fig, ax = _fig(4.8, 4.4)
    ax.plot(reference_cm3, measured_cm3, "o", color="#1f77b4", label="rocks")
    lo = min(min(reference_cm3), min(measured_cm3)) * 0.9
    hi = max(max(reference_cm3), max(measured_cm3)) * 1.1
    ax.plot([lo, hi], [lo, hi], "k--", lw=1, label="1:1")
    ax.set_xlim(lo, hi)
    ax.set_ylim(lo, hi)
    ax.set_xlabel("reference volume (cm³)")
    ax.set_ylabel("reconstructed volume (cm³)")
    ax.set_title(f"MPE {mpe:+.2f} %, MAPE {mape:.2f} % ({len(ids)} rocks)", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def batch_figure7(rows, key3d, key2d, label3d, label2d):
    """Per rock, sorted by the 3D figure: the 3D value, the views' 2D mean
    with its min-max bar, and below it the 2D figure's CoV (the study's
    Figure 7)."""
    rows = sorted(rows, key=lambda r: r[key3d])
    x = np.arange(len(rows))
    fig, (ax, axc) = _fig(7.2, 4.6, 2, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    mean = np.array([r[key2d]["mean"] for r in rows])
    lo = mean - np.array([r[key2d]["min"] for r in rows])
    hi = np.array([r[key2d]["max"] for r in rows]) - mean
    ax.errorbar(x, mean, yerr=[lo, hi], fmt="o", color="#1f77b4", ms=4, capsize=2,
                label=f"{label2d}: mean, min-max of the views")
    ax.plot(x, [r[key3d] for r in rows], "s", color="k", ms=5, label=label3d)
    ax.set_ylabel(label3d)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    axc.bar(x, [100.0 * (r[key2d]["cov"] or 0) for r in rows], color="#7f7f7f")
    axc.set_ylabel("CoV (%)", fontsize=8)
    axc.set_xticks(x)
    axc.set_xticklabels([r["id"] for r in rows], rotation=90, fontsize=6)
    axc.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    return fig


def batch_figure8(rows):
    """Per rock, sorted by the mean 2D FER: c/b and b/a against it (the
    study's Figure 8)."""
    rows = sorted(rows, key=lambda r: r["fer_2d"]["mean"])
    x = np.arange(len(rows))
    fig, ax = _fig(7.2, 3.6)
    ax.plot(x, [r["fer_2d"]["mean"] for r in rows], "o", color="k", ms=5, label="mean 2D FER")
    ax.plot(x, [r["ratio_c_b"] for r in rows], "s", color="#1f77b4", ms=4, label="c/b")
    ax.plot(x, [r["ratio_b_a"] for r in rows], "^", color="#d62728", ms=4, label="b/a")
    ax.set_xticks(x)
    ax.set_xticklabels([r["id"] for r in rows], rotation=90, fontsize=6)
    ax.set_ylabel("ratio")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def gradation_curve(curve_kg, points, spec_rows):
    """Percent lighter by mass against stone mass (log axis), the
    characteristic masses, and a specification's control points as bands."""
    fig, ax = _fig(6.4, 4.2)
    ax.semilogx([m for m, _ in curve_kg], [p for _, p in curve_kg], "o-", color="#1f77b4",
                ms=3, lw=1, label="batch")
    for k in ("W15", "W50", "W85", "W100"):
        v = points.get(k, {}).get("value")
        if v:
            ax.axvline(v, color="#7f7f7f", lw=0.6, ls=":")
            ax.text(v, 2, k, rotation=90, fontsize=6, va="bottom", ha="right")
    for r in spec_rows or []:
        if r["quantity"] != "mass":
            continue
        lo = r["min"] if r["min"] is not None else 0
        hi = r["max"] if r["max"] is not None else 100
        ax.plot([r["value"], r["value"]], [lo, hi], "-", lw=4, alpha=0.5,
                color="#2ca02c" if r["pass"] else "#d62728")
        ax.plot([r["value"]], [r["percent"]], "x", color="k", ms=6)
    ax.set_xlabel("stone mass (kg)")
    ax.set_ylabel("percent lighter by mass (%)")
    ax.set_ylim(0, 102)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def distributions(sphericity, fer):
    """Histograms of sphericity and 3D FER across the batch."""
    fig, (a1, a2) = _fig(7.2, 2.8, 1, 2)
    a1.hist(sphericity, bins=min(10, max(3, len(sphericity) // 3)), color="#1f77b4",
            edgecolor="k")
    a1.set_xlabel("sphericity")
    a1.set_ylabel("rocks")
    a2.hist(fer, bins=min(10, max(3, len(fer) // 3)), color="#d62728", edgecolor="k")
    a2.set_xlabel("3D FER (c/a)")
    for a in (a1, a2):
        a.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def count_data_points(fig):
    """How many data points a figure's axes hold (lines' vertices,
    collections' offsets and paths): a check that a figure is not empty."""
    n = 0
    for ax in fig.axes:
        for line in ax.get_lines():
            n += len(line.get_xdata())
        for c in ax.collections:
            n += max(len(c.get_offsets()), len(c.get_paths()))
        n += len(ax.patches)
    return n

