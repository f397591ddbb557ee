#!/usr/bin/python3
"""Makes aggscan's QA reports, per rock and per batch, as HTML and PDF.

`aggscan report` gathers a sample's (or a batch's) records from the state
directory into one JSON document and runs this on it:

    aggscan_report.py --input DOC.json [--html OUT.html] [--pdf OUT.pdf]
                      [--spec FILE.toml]

Plots come from matplotlib, the PDF from WeasyPrint laying out the same HTML
(Debian's python3-matplotlib and weasyprint). Exit codes: 0 written, 2 the
input cannot make a report (the message says what to do), 3 a library is
missing.
"""

import argparse
import base64
import html
import io
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import report_math as rm  # noqa: E402

try:
    import report_figures as rf  # noqa: E402
except ImportError as e:  # pragma: no cover - depends on the machine
    print(f"aggscan report: matplotlib is missing ({e}): apt-get install python3-matplotlib",
          file=sys.stderr)
    sys.exit(3)

E = html.escape


def num(v, decimals=1, unit=""):
    """A number in plain decimals, or a dash."""
    if v is None:
        return "–"
    try:
        return f"{float(v):.{decimals}f}" + (f" {unit}" if unit else "")
    except (TypeError, ValueError):
        return "–"


def svg(fig):
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="svg")
    plt.close(fig)
    return "data:image/svg+xml;base64," + base64.b64encode(buf.getvalue()).decode()


def png(fig, dpi=110):
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def img(uri, caption, cls="fig"):
    return (f'<figure class="{cls}"><img src="{uri}" alt="{E(caption)}">'
            f"<figcaption>{E(caption)}</figcaption></figure>")


CSS = """
@page { size: A4; margin: 14mm 12mm; @bottom-right { content: counter(page) " / " counter(pages);
  font-size: 8pt; } }
body { font-family: "DejaVu Sans", sans-serif; font-size: 9pt; color: #111; }
h1 { font-size: 15pt; margin: 0 0 4pt 0; } h2 { font-size: 11.5pt; margin: 12pt 0 4pt 0;
  border-bottom: 1px solid #999; } h3 { font-size: 10pt; margin: 8pt 0 3pt 0; }
table { border-collapse: collapse; margin: 3pt 0; font-size: 7.5pt; } td, th {
  border: 1px solid #bbb; padding: 1.5pt 3pt; text-align: right; } th { background: #eee; } td.l, th.l { text-align: left; }
.pass { color: #176117; font-weight: bold; } .warn { color: #a15c00; font-weight: bold; }
.fail { color: #b00; font-weight: bold; }
figure { margin: 4pt 0; page-break-inside: avoid; } figure img { max-width: 100%; }
figcaption { font-size: 8pt; color: #444; } .photos figure { display: inline-block;
  width: 32%; margin: 0 0.5% 4pt 0; } .photos img { width: 100%; }
.small { font-size: 8pt; color: #444; } .note { font-size: 8pt; }
"""


def page(title, body):
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{E(title)}</title>"
            f"<style>{CSS}</style></head><body>{body}</body></html>")


def table(header, rows, left=0):
    """A table; the first `left` columns left-aligned."""
    h = "".join(f'<th class="{"l" if i < left else ""}">{E(c)}</th>' for i, c in enumerate(header))
    body = ""
    for r in rows:
        cells = []
        for i, c in enumerate(r):
            raw = isinstance(c, tuple)  # (html, css class): already escaped
            text, cls = (c if raw else (E(str(c)), ""))
            cls = " ".join(x for x in ("l" if i < left else "", cls) if x)
            cells.append(f'<td class="{cls}">{text}</td>')
        body += "<tr>" + "".join(cells) + "</tr>"
    return f"<table><thead><tr>{h}</tr></thead><tbody>{body}</tbody></table>"


# --- the data of one rock -------------------------------------------------------


def rock_row(s):
    """The figures of a sample the reports use, from its morphology record
    and its description; None when it has no 3D figures."""
    m = s.get("morphology") or {}
    d3 = m.get("morphology_3d") or {}
    if not isinstance(d3.get("volume_mm3"), (int, float)):
        return None
    overall = (m.get("stats_2d") or {}).get("overall") or {}
    return {
        "id": s["id"],
        "volume_mm3": d3.get("volume_mm3"),
        "area_mm2": d3.get("surface_area_mm2"),
        "a_mm": d3.get("a_mm"), "b_mm": d3.get("b_mm"), "c_mm": d3.get("c_mm"),
        "fer_3d": d3.get("fer_3d"), "ratio_c_b": d3.get("ratio_c_b"),
        "ratio_b_a": d3.get("ratio_b_a"), "sphericity": d3.get("sphericity"),
        "fer_2d": overall.get("fer_2d") or {}, "circularity": overall.get("circularity") or {},
        "mass_kg": (s["mass_g"] / 1000.0) if s.get("mass_g") is not None else None,
        "mass_none": s.get("mass_none"),
        "reference_mm3": s.get("reference_volume_mm3"),
        "confident": (m.get("quality") or {}).get("confident", False)
        and not (m.get("quality") or {}).get("flags"),
        "flags": (m.get("quality") or {}).get("flags") or [],
        "views": m.get("views_2d") or [],
    }


def table1(rows):
    header = ["rock", "V (cm³)", "A (cm²)", "a (mm)", "b (mm)", "c (mm)", "FER c/a", "c/b",
              "b/a", "sphericity", "mass (kg)", "quality"]
    out = []
    for r in rows:
        q = ("ok", "pass") if r["confident"] else (
            ", ".join(f.get("code", "") for f in r["flags"]) or "flagged", "warn")
        out.append([r["id"], num(r["volume_mm3"] / 1000.0, 2), num(r["area_mm2"] / 100.0, 2),
                    num(r["a_mm"], 1), num(r["b_mm"], 1), num(r["c_mm"], 1),
                    num(r["fer_3d"], 3), num(r["ratio_c_b"], 3), num(r["ratio_b_a"], 3),
                    num(r["sphericity"], 3), num(r["mass_kg"], 3), (E(q[0]), q[1])])
    return table(header, out, left=1)


def quality_rows(m):
    """Quality figures against the limits behind the worker's flags."""
    q = m.get("quality") or {}
    checks = [
        ("masks' IoU with the model's silhouettes, mean", q.get("silhouette_iou_mean"), 4,
         ">= 0.97", lambda v: v >= 0.97),
        ("masks' IoU, worst view", q.get("silhouette_iou_min"), 4, ">= 0.95",
         lambda v: v >= 0.95),
        ("stitch RMS (mm)", q.get("stitch_rms_mm"), 3, "<= 1.0", lambda v: v <= 1.0),
        ("scale residual (mm)", q.get("scale_residual_mm"), 3, "<= 0.5", lambda v: v <= 0.5),
        ("rig calibration RMS (px)", q.get("calibration_reprojection_rms_px"), 3, "", None),
        ("mesh closed and manifold", q.get("watertight"), None, "yes", lambda v: bool(v)),
    ]
    rows = []
    for name, v, dec, limit, ok in checks:
        if v is None:
            continue
        shown = ("yes" if v else "no") if dec is None else num(v, dec)
        if ok is None:
            verdict = ("", "")
        else:
            verdict = ("pass", "pass") if ok(v) else ("warn", "warn")
        rows.append([name, shown, limit, verdict])
    return rows


def rock_report(doc):
    s = doc["samples"][0]
    m = s.get("morphology") or {}
    r = rock_row(s)
    meta = s.get("meta") or {}
    mat = meta.get("material") or {}
    title = f"Rock {s['id']}"
    body = [f"<h1>{E(title)}</h1>",
            f"<p class='small'>report made {E(doc.get('generated_utc', ''))} by aggscan "
            f"{E(doc.get('software_version', ''))}</p>"]
    ident = [["sample", s["id"]], ["captured (UTC)", s.get("created_utc", "")],
             ["state", s.get("state", "")], ["operator", meta.get("operator", "–")],
             ["source / lot", meta.get("lot", "–")],
             ["material", mat.get("name", "–")],
             ["specific gravity", (num(mat.get("specific_gravity"), 3) + f" ({mat.get('basis', '')})")
              if mat.get("specific_gravity") else "not given: no mass"],
             ["notes", meta.get("notes", "–")]]
    body.append("<h2>Identification</h2>" + table(["", ""], ident, left=2))
    if r is None:
        body.append("<p class='fail'>This sample has no 3D figures yet: "
                    f"{E(s.get('why_no_result', 'it has not been reconstructed'))}.</p>")
        return title, page(title, "".join(body))
    body.append("<h2>Figures (the study's Table 1)</h2>" + table1([r]))
    mass_line = (f"Mass {num(r['mass_kg'], 3)} kg = volume × specific gravity "
                 f"{num(mat.get('specific_gravity'), 3)} ({E(mat.get('basis', ''))}) × 1 g/cm³."
                 if r["mass_kg"] is not None else f"No mass: {E(r['mass_none'] or '')}")
    body.append(f"<p class='note'>{mass_line}</p>")
    photos = s.get("photos") or []
    if photos:
        body.append("<h2>Photos with the mask's outline</h2><div class='photos'>")
        for p in photos:
            try:
                uri = png(rf.photo_with_outline(p["image"], p.get("mask"),
                                                f"side {p['side']}, view {p['view']}"), 100)
                body.append(img(uri, f"side {p['side']}, view {p['view']}"))
            except (OSError, ValueError) as e:
                body.append(f"<p class='warn'>side {p['side']} view {p['view']}: "
                            f"{E(str(e))}</p>")
        body.append("</div>")
    if s.get("mesh"):
        try:
            body.append("<h2>The model</h2>" + img(png(rf.mesh_views(s["mesh"]), 120),
                                                   "the reconstructed surface from three "
                                                   "directions (orthographic, mm)"))
        except (OSError, ValueError) as e:
            body.append(f"<p class='warn'>the mesh could not be drawn: {E(str(e))}</p>")
    views = [v for v in r["views"] if isinstance(v.get("fer_2d"), (int, float))]
    if views and r["fer_2d"].get("mean") is not None:
        body.append("<h2>2D against 3D (the study's Figures 7 and 8)</h2>")
        body.append(img(svg(rf.rock_figure7(views, r["fer_3d"], r["sphericity"])),
                        "Figure 7: each view's 2D FER and circularity against the 3D FER and "
                        "sphericity"))
        body.append(img(svg(rf.rock_figure8(r["fer_2d"], r["ratio_c_b"], r["ratio_b_a"])),
                        "Figure 8: mean 2D FER against c/b and b/a"))
        f2, c2 = r["fer_2d"], r["circularity"]
        body.append(table(["2D figure", "mean", "min", "max", "CoV (%)", "views"],
                          [["FER", num(f2.get("mean"), 3), num(f2.get("min"), 3),
                            num(f2.get("max"), 3), num(100 * (f2.get("cov") or 0), 1),
                            f2.get("n", "")],
                           ["circularity", num(c2.get("mean"), 3), num(c2.get("min"), 3),
                            num(c2.get("max"), 3), num(100 * (c2.get("cov") or 0), 1),
                            c2.get("n", "")]], left=1))
    body.append("<h2>Quality</h2>" + table(["figure", "value", "limit", ""], quality_rows(m),
                                           left=1))
    if r["flags"]:
        body.append("<p class='warn'>NOT CONFIDENT: " + "; ".join(
            E(f"{f.get('code', '')}: {f.get('reason', '')}") for f in r["flags"]) + "</p>")
    else:
        body.append("<p class='pass'>Confident: no quality flag raised.</p>")
    for w in m.get("warnings") or []:
        body.append(f"<p class='warn'>{E(str(w))}</p>")
    methods = m.get("methods") or {}
    t = m.get("timings_s") or {}
    sw = m.get("software") or {}
    body.append("<h2>Methods, timings, software</h2>" + table(
        ["", ""],
        [[k, v] for k, v in methods.items()]
        + [["worker time (s)", num(t.get("total"), 1)],
           ["software", sw.get("version", "(not recorded)")],
           ["config SHA-256", sw.get("config_sha256", "(not recorded)")]], left=2))
    return title, page(title, "".join(body))


# --- a batch ------------------------------------------------------------------


def batch_report(doc, spec_path):
    batch = doc.get("batch") or {}
    name = batch.get("name", "")
    title = f"Batch {name}"
    rows, skipped = [], []
    for s in doc["samples"]:
        r = rock_row(s)
        (rows.append(r) if r else skipped.append(s["id"]))
    if not rows:
        raise rm.ReportError(f"batch {name} has no reconstructed rock"
                             + (f" (samples without figures: {', '.join(skipped)})"
                                if skipped else ""))
    no_mass = [r["id"] for r in rows if r["mass_kg"] is None]
    if no_mass:
        raise rm.ReportError(
            "no specific gravity for " + ", ".join(no_mass) + ": the gradation and the shares "
            "by mass need every rock's mass; give it with `aggscan meta ID --sg 2.65 --sg-basis "
            "bulk-ssd` (or [material] specific_gravity for new samples)")
    spec = rm.load_spec(spec_path) if spec_path else None
    body = [f"<h1>{E(title)}</h1>",
            f"<p class='small'>report made {E(doc.get('generated_utc', ''))} by aggscan "
            f"{E(doc.get('software_version', ''))}</p>"]
    crit = [["rocks with figures", str(len(rows))]]
    for k, label in (("lot", "lot"), ("from", "created from"), ("to", "created to"),
                     ("notes", "notes")):
        if batch.get(k):
            crit.append([label, batch[k]])
    if batch.get("samples"):
        crit.append(["listed", ", ".join(batch["samples"])])
    if skipped:
        crit.append(["without figures (left out)", ", ".join(skipped)])
    if batch.get("missing"):
        crit.append(["listed but not on the rig", ", ".join(batch["missing"])])
    body.append("<h2>The batch</h2>" + table(["", ""], crit, left=2))
    body.append("<h2>Table 1: every rock</h2>" + table1(rows))

    masses = [r["mass_kg"] for r in rows]
    b = [r["b_mm"] for r in rows]
    # Gradation.
    curve = rm.cumulative_curve(masses, masses)
    pts = rm.characteristic_points(masses, b)
    spec_rows, passed = (rm.check_spec(spec, masses, b) if spec else ([], None))
    body.append("<h2>Gradation by mass</h2>")
    body.append(img(svg(rf.gradation_curve(curve, pts, spec_rows)),
                    "percent of the batch's mass lighter than each stone (log axis)"))
    char = []
    for k in ("W15", "W50", "W85", "W100"):
        p = pts[k]
        char.append([k, num(p["value"], 3, "kg") if p["value"] is not None else p["why"]])
    for k in ("D15", "D50", "D85"):
        p = pts[k]
        char.append([k + " (b, by mass)",
                     num(p["value"], 1, "mm") if p["value"] is not None else p["why"]])
    body.append(table(["point", "value"], char, left=2))
    if spec:
        srows = []
        for sr in spec_rows:
            band = (f"{'' if sr['min'] is None else num(sr['min'], 0)}"
                    f"–{'' if sr['max'] is None else num(sr['max'], 0)}")
            if sr["quantity"].startswith("range"):
                unit = "kg" if sr["quantity"] == "range mass" else "mm"
                name = ("W" if unit == "kg" else "D") + f"{sr['percent_of']:g}"
                lim = (f"{name} by {sr['basis']} in {sr['min']:g}–{sr['max']:g} {unit}")
                shown = (num(sr["value"], 3 if unit == "kg" else 1, unit)
                         if sr["value"] is not None else sr["why"])
            elif sr["quantity"] == "mean mass":
                shown, lim = num(sr["value"], 2, "kg"), f"{num(sr['min'], 1)}–{num(sr['max'], 1)} kg"
            else:
                unit = "kg" if sr["quantity"] == "mass" else "mm (b)"
                shown, lim = num(sr["percent"], 1, "%"), f"{band} % lighter than {sr['value']:g} {unit}"
            srows.append([sr["label"], lim, shown,
                          ("pass", "pass") if sr["pass"] else ("FAIL", "fail")])
        body.append(f"<h3>Against {E(spec['name'])}</h3>"
                    f"<p class='small'>{E(spec.get('source', ''))}</p>"
                    + table(["control point", "required", "batch", ""], srows, left=1)
                    + (f"<p class='{'pass' if passed else 'fail'}'>"
                       f"{'The batch meets' if passed else 'The batch does NOT meet'} "
                       f"{E(spec['name'])} ({len(rows)} rocks).</p>"))
    # Shape.
    fe = rm.flat_elongated([r["fer_3d"] for r in rows], masses)
    body.append("<h2>Flat and elongated (ASTM D4791, c/a)</h2>" + table(
        ["ratio", "rocks", "by count (%)", "by mass (%)"],
        [[f"> {f['ratio']:g}:1", str(f["count"]), num(f["by_count"], 1), num(f["by_mass"], 1)]
         for f in fe], left=1))
    body.append(img(svg(rf.distributions([r["sphericity"] for r in rows],
                                         [r["fer_3d"] for r in rows])),
                    "distributions of sphericity and 3D FER"))
    with_2d = [r for r in rows if r["fer_2d"].get("mean") is not None
               and r["circularity"].get("mean") is not None]
    if with_2d:
        body.append("<h2>2D against 3D (the study's Figures 7 and 8)</h2>")
        body.append(img(svg(rf.batch_figure7(with_2d, "fer_3d", "fer_2d", "3D FER",
                                              "2D FER of the views")),
                        "Figure 7a: 3D FER and the views' 2D FER (sorted by 3D FER; CoV below)"))
        body.append(img(svg(rf.batch_figure7(with_2d, "sphericity", "circularity", "sphericity",
                                              "circularity of the views")),
                        "Figure 7b: sphericity and the views' circularity (sorted; CoV below)"))
        body.append(img(svg(rf.batch_figure8(with_2d)),
                        "Figure 8: mean 2D FER against c/b and b/a (sorted by mean 2D FER)"))
        ratio = rm.stats([r["fer_3d"] / r["fer_2d"]["mean"] for r in with_2d
                          if r["fer_2d"]["mean"]])
        f3 = rm.stats([r["fer_3d"] for r in with_2d])
        f2 = rm.stats([r["fer_2d"]["mean"] for r in with_2d])
        body.append("<h3>Correction factor: 3D FER over mean 2D FER</h3>" + table(
            ["", "rocks", "value", "std", "min", "max", "CoV (%)"],
            [["mean 3D FER / mean 2D FER of the batch", str(f3["n"]),
              num(f3["mean"] / f2["mean"] if f2["mean"] else None, 3), "", "", "", ""],
             ["per rock: 3D FER / its views' mean 2D FER", str(ratio["n"]), num(ratio["mean"], 3),
              num(ratio["std"], 3), num(ratio["min"], 3), num(ratio["max"], 3),
              num(100 * (ratio["cov"] or 0), 1)]], left=1))
    ref = [r for r in rows if r["reference_mm3"]]
    body.append("<h2>Reconstructed against reference volumes (the study's Figure 6)</h2>")
    if ref:
        e = rm.volume_errors([r["volume_mm3"] for r in ref], [r["reference_mm3"] for r in ref])
        body.append(img(svg(rf.batch_figure6([r["id"] for r in ref],
                                             [r["volume_mm3"] / 1000 for r in ref],
                                             [r["reference_mm3"] / 1000 for r in ref],
                                             e["mpe"], e["mape"])),
                        "Figure 6: reconstructed against reference volume"))
        body.append(table(["rock", "reference (cm³)", "reconstructed (cm³)", "error (%)"],
                          [[r["id"], num(r["reference_mm3"] / 1000, 2),
                            num(r["volume_mm3"] / 1000, 2), num(err, 2)]
                           for r, err in zip(ref, e["errors"])], left=1)
                    + f"<p>MPE {num(e['mpe'], 2)} %, MAPE {num(e['mape'], 2)} % over "
                      f"{e['n']} rocks.</p>")
    else:
        body.append("<p class='note'>No reference volumes imported (`aggscan reference import "
                    "CSV`).</p>")
    flagged = [r for r in rows if not r["confident"]]
    body.append("<h2>Quality</h2>" + (
        "<p class='pass'>Every rock is confident.</p>" if not flagged else
        "<p class='warn'>Not confident: " + "; ".join(
            E(r["id"] + " (" + ", ".join(f.get("code", "") for f in r["flags"]) + ")")
            for r in flagged) + "</p>"))
    return title, page(title, "".join(body))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--input", required=True, help="the report document (JSON)")
    ap.add_argument("--html", help="write the HTML here")
    ap.add_argument("--pdf", help="write the PDF here")
    ap.add_argument("--spec", help="gradation specification (TOML) for a batch")
    a = ap.parse_args(argv)
    if not a.html and not a.pdf:
        ap.error("give --html FILE and/or --pdf FILE")
    t0 = time.monotonic()
    try:
        with open(a.input, encoding="utf-8") as f:
            doc = json.load(f)
        if doc.get("kind") == "batch":
            _, text = batch_report(doc, a.spec)
        else:
            _, text = rock_report(doc)
    except rm.ReportError as e:
        print(f"aggscan report: {e}", file=sys.stderr)
        return 2
    except (OSError, ValueError, KeyError) as e:
        print(f"aggscan report: the report document {a.input} does not read: {e}",
              file=sys.stderr)
        return 2
    if a.html:
        with open(a.html, "w", encoding="utf-8") as f:
            f.write(text)
    if a.pdf:
        try:
            from weasyprint import HTML
        except ImportError as e:
            print(f"aggscan report: WeasyPrint is missing ({e}): apt-get install weasyprint",
                  file=sys.stderr)
            return 3
        HTML(string=text).write_pdf(a.pdf)
    print(json.dumps({"seconds": round(time.monotonic() - t0, 2),
                      "html": a.html, "pdf": a.pdf}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
