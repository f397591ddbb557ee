"""The arithmetic of the QA reports: gradation by mass, the characteristic
masses and intermediate dimensions, a gradation specification's control
points, ASTM D4791 flat-and-elongated shares, and summary statistics.

Pure Python (no numpy, no matplotlib): the report's numbers do not depend on
the plotting stack, and these functions are tested on hand-computed cases
(tests/report/report_math_test.py).
"""

import math
import tomllib

# Characteristic points reported for every batch.
MASS_PERCENTS = (15, 50, 85, 100)  # W15, W50, W85, W100
SIZE_PERCENTS = (15, 50, 85)  # D15, D50, D85 of the intermediate dimension b
FE_RATIOS = (2.0, 3.0, 5.0)  # ASTM D4791 ratios of length to thickness


class ReportError(Exception):
    """Input the report cannot be made from; the message says what to do."""


def cumulative_curve(values, weights):
    """Sorts the stones by `values` (mass, or the intermediate dimension) and
    returns [(value, percent)]: the percentage of the batch's total weight in
    stones whose value is at most this one (the stone itself included), as a
    gradation curve by weighing individual stones plots it."""
    if len(values) != len(weights):
        raise ValueError("values and weights differ in length")
    pairs = sorted(zip(values, weights))
    total = sum(w for _, w in pairs)
    if not pairs or total <= 0:
        return []
    out, acc = [], 0.0
    for v, w in pairs:
        acc += w
        out.append((v, 100.0 * acc / total))
    out[-1] = (out[-1][0], 100.0)  # no rounding residue at the top
    return out


def value_at_percent(curve, percent):
    """The value (W_x or D_x) at which `percent` of the weight is reached,
    interpolated linearly in log(value) between neighbouring stones, as the
    curve is drawn on a log axis. Returns (value, None) or (None, reason):
    below the lightest stone's own share the batch cannot resolve it."""
    if not curve:
        return None, "no stones"
    if percent >= 100.0:
        return curve[-1][0], None
    v0, p0 = curve[0]
    if percent < p0:
        return None, (
            f"not determined: the first stone alone makes {p0:.1f} % of the batch; "
            f"the batch is too small to resolve {percent:g} % (measure more stones)")
    if percent == p0:
        return v0, None
    for (va, pa), (vb, pb) in zip(curve, curve[1:]):
        if pa <= percent <= pb:
            if pb == pa or va <= 0 or vb <= 0:
                return vb, None
            t = (percent - pa) / (pb - pa)
            return math.exp(math.log(va) + t * (math.log(vb) - math.log(va))), None
    return curve[-1][0], None


def percent_lighter_than(masses, limit):
    """The percentage of the batch's mass in stones lighter than `limit`
    (a specification's control point: no interpolation, the stones as they
    are)."""
    total = sum(masses)
    if total <= 0:
        return 0.0
    return 100.0 * sum(m for m in masses if m < limit) / total


def characteristic_points(masses_kg, b_mm):
    """W15/W50/W85/W100 (kg) and D15/D50/D85 of b (mm, by mass):
    {"W50": {"value": v, "why": None}, ...}."""
    out = {}
    curve = cumulative_curve(masses_kg, masses_kg)
    for p in MASS_PERCENTS:
        v, why = value_at_percent(curve, p)
        out[f"W{p}"] = {"value": v, "why": why}
    size_curve = cumulative_curve(b_mm, masses_kg)
    for p in SIZE_PERCENTS:
        v, why = value_at_percent(size_curve, p)
        out[f"D{p}"] = {"value": v, "why": why}
    return out


def load_spec(path):
    """A gradation specification (scripts/report/specs/*.toml): name, source,
    and its checks. [[point]]: a limit and the share of the batch's mass
    below it, {label, quantity ("mass" in kg or "b" in mm), value,
    min_percent_lighter and/or max_percent_lighter}. [[range]]: the value at
    which a share of the batch is reached must lie in a range, {label,
    percent, basis ("count" or "mass"), quantity ("mass" or "b"), min, max}
    (FHWA FP-14's form: D15..D100 and W15..W100 by count). Optional
    mean_mass_kg = [min, max]."""
    try:
        with open(path, "rb") as f:
            spec = tomllib.load(f)
    except FileNotFoundError:
        raise ReportError(f"gradation specification {path} does not exist")
    except tomllib.TOMLDecodeError as e:
        raise ReportError(f"gradation specification {path} is not valid TOML: {e}")
    if not isinstance(spec.get("name"), str) or not spec["name"]:
        raise ReportError(f"{path}: give the specification a name = \"...\"")
    points = spec.get("point", [])
    ranges = spec.get("range", [])
    if not isinstance(points, list) or not isinstance(ranges, list) or not (points or ranges):
        raise ReportError(f"{path}: no [[point]] or [[range]] checks")
    for i, r in enumerate(ranges):
        where = f"{path}: range {i + 1}"
        if r.get("quantity", "b") not in ("mass", "b"):
            raise ReportError(f"{where}: quantity must be \"mass\" (kg) or \"b\" (mm)")
        if r.get("basis", "count") not in ("count", "mass"):
            raise ReportError(f"{where}: basis must be \"count\" or \"mass\"")
        pct = r.get("percent")
        if not isinstance(pct, (int, float)) or not 0 < pct <= 100:
            raise ReportError(f"{where}: percent must be above 0 and at most 100")
        lo, hi = r.get("min"), r.get("max")
        if not all(isinstance(x, (int, float)) and x > 0 for x in (lo, hi)) or lo > hi:
            raise ReportError(f"{where}: give min and max, positive, min <= max")
    for i, p in enumerate(points):
        where = f"{path}: point {i + 1}"
        if p.get("quantity", "mass") not in ("mass", "b"):
            raise ReportError(f"{where}: quantity must be \"mass\" (kg) or \"b\" (mm)")
        v = p.get("value")
        if not isinstance(v, (int, float)) or v <= 0:
            raise ReportError(f"{where}: value must be a positive number (kg or mm)")
        lo, hi = p.get("min_percent_lighter"), p.get("max_percent_lighter")
        if lo is None and hi is None:
            raise ReportError(f"{where}: give min_percent_lighter and/or max_percent_lighter")
        for x in (lo, hi):
            if x is not None and (not isinstance(x, (int, float)) or not 0 <= x <= 100):
                raise ReportError(f"{where}: percentages are 0 to 100")
        if lo is not None and hi is not None and lo > hi:
            raise ReportError(f"{where}: min_percent_lighter is above max_percent_lighter")
    mem = spec.get("mean_mass_kg")
    if mem is not None and (not isinstance(mem, list) or len(mem) != 2 or mem[0] > mem[1]):
        raise ReportError(f"{path}: mean_mass_kg must be [min, max]")
    return spec


def check_spec(spec, masses_kg, b_mm):
    """Each control point with the batch's percentage lighter (by mass) and
    pass/fail; the mean mass against its range. Returns (rows, passed)."""
    rows = []
    for r in spec.get("range", []):
        quantity = r.get("quantity", "b")
        values = masses_kg if quantity == "mass" else b_mm
        weights = [1.0] * len(values) if r.get("basis", "count") == "count" else masses_kg
        v, why = value_at_percent(cumulative_curve(values, weights), r["percent"])
        ok = v is not None and r["min"] <= v <= r["max"]
        rows.append({"label": r.get("label", ""), "quantity": "range " + quantity,
                     "basis": r.get("basis", "count"), "percent_of": r["percent"], "value": v,
                     "why": why, "min": r["min"], "max": r["max"], "percent": None, "pass": ok})
    for p in spec.get("point", []):
        quantity = p.get("quantity", "mass")
        if quantity == "mass":
            pct = percent_lighter_than(masses_kg, p["value"])
        else:
            total = sum(masses_kg)
            pct = 100.0 * sum(m for m, b in zip(masses_kg, b_mm) if b < p["value"]) / total
        lo, hi = p.get("min_percent_lighter"), p.get("max_percent_lighter")
        ok = (lo is None or pct >= lo) and (hi is None or pct <= hi)
        rows.append({"label": p.get("label", ""), "quantity": quantity, "value": p["value"],
                     "min": lo, "max": hi, "percent": pct, "pass": ok})
    mem = spec.get("mean_mass_kg")
    if mem is not None and masses_kg:
        mean = sum(masses_kg) / len(masses_kg)
        rows.append({"label": "mean mass", "quantity": "mean mass", "value": mean,
                     "min": mem[0], "max": mem[1], "percent": None,
                     "pass": mem[0] <= mean <= mem[1]})
    return rows, all(r["pass"] for r in rows)


def flat_elongated(ratios, masses, limits=FE_RATIOS):
    """ASTM D4791: the share of particles whose length-to-thickness ratio
    (c/a) is greater than each limit, by count and by mass (percent)."""
    n = len(ratios)
    total = sum(masses) if masses else 0.0
    out = []
    for r in limits:
        hits = [i for i, x in enumerate(ratios) if x > r]
        by_count = 100.0 * len(hits) / n if n else 0.0
        by_mass = 100.0 * sum(masses[i] for i in hits) / total if total > 0 else None
        out.append({"ratio": r, "count": len(hits), "by_count": by_count, "by_mass": by_mass})
    return out


def stats(values):
    """mean, sample standard deviation, min, max, CoV (std / mean), n."""
    v = [x for x in values if x is not None and math.isfinite(x)]
    n = len(v)
    if n == 0:
        return {"n": 0, "mean": None, "std": None, "min": None, "max": None, "cov": None}
    mean = sum(v) / n
    std = math.sqrt(sum((x - mean) ** 2 for x in v) / (n - 1)) if n > 1 else 0.0
    return {"n": n, "mean": mean, "std": std, "min": min(v), "max": max(v),
            "cov": std / mean if mean else None}


def volume_errors(measured, reference):
    """Percentage errors of measured against reference volumes, MPE (signed
    mean) and MAPE (mean of absolute), as the study's Figure 6 reports them."""
    errs = [100.0 * (m - r) / r for m, r in zip(measured, reference) if r]
    if not errs:
        return {"n": 0, "mpe": None, "mape": None, "errors": []}
    return {"n": len(errs), "mpe": sum(errs) / len(errs),
            "mape": sum(abs(e) for e in errs) / len(errs), "errors": errs}
