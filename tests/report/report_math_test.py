"""The report's arithmetic against hand-computed cases."""

import math
import os
import sys
import tempfile
import unittest

sys.path.insert(0, os.path.join(os.environ.get("AGGSCAN_SOURCE_DIR", "."), "scripts", "report"))
import report_math as rm  # noqa: E402

# Five stones of 1, 2, 3, 4 and 10 kg (20 kg in all): sorted, the batch's
# mass in stones at most as heavy as each is 1, 3, 6, 10, 20 kg, i.e. 5, 15,
# 30, 50 and 100 %.
MASSES = [4.0, 1.0, 10.0, 3.0, 2.0]
B_MM = [160.0, 100.0, 230.0, 150.0, 120.0]


class Gradation(unittest.TestCase):
    def test_curve(self):
        curve = rm.cumulative_curve(MASSES, MASSES)
        self.assertEqual([v for v, _ in curve], [1.0, 2.0, 3.0, 4.0, 10.0])
        for (_, p), want in zip(curve, [5.0, 15.0, 30.0, 50.0, 100.0]):
            self.assertAlmostEqual(p, want)

    def test_characteristic_masses(self):
        curve = rm.cumulative_curve(MASSES, MASSES)
        self.assertAlmostEqual(rm.value_at_percent(curve, 15)[0], 2.0)
        self.assertAlmostEqual(rm.value_at_percent(curve, 50)[0], 4.0)
        self.assertAlmostEqual(rm.value_at_percent(curve, 100)[0], 10.0)
        # Between stones: linear in log(mass). 85 % is 0.7 of the way from
        # (4 kg, 50 %) to (10 kg, 100 %): 4 x 2.5^0.7 = 7.5967 kg.
        self.assertAlmostEqual(rm.value_at_percent(curve, 85)[0], 4.0 * 2.5 ** 0.7)
        self.assertAlmostEqual(rm.value_at_percent(curve, 85)[0], 7.5967, places=3)
        # 40 % is halfway from (3 kg, 30 %) to (4 kg, 50 %): sqrt(12).
        self.assertAlmostEqual(rm.value_at_percent(curve, 40)[0], math.sqrt(12.0))

    def test_batch_too_small_for_a_point_says_so(self):
        curve = rm.cumulative_curve(MASSES, MASSES)
        value, why = rm.value_at_percent(curve, 3)
        self.assertIsNone(value)
        self.assertIn("too small", why)
        self.assertIn("5.0 %", why)
        # Two stones of 1 and 9 kg: W15 needs a stone below 10 %.
        pts = rm.characteristic_points([9.0, 1.0], [200.0, 90.0])
        self.assertIsNotNone(pts["W15"]["value"])
        pts = rm.characteristic_points([9.0, 3.0], [200.0, 90.0])
        self.assertIsNone(pts["W15"]["value"])
        self.assertIn("25.0 %", pts["W15"]["why"])
        self.assertIsNone(rm.value_at_percent([], 50)[0])

    def test_intermediate_dimension_by_mass(self):
        pts = rm.characteristic_points(MASSES, B_MM)
        self.assertAlmostEqual(pts["D15"]["value"], 120.0)
        self.assertAlmostEqual(pts["D50"]["value"], 160.0)
        self.assertAlmostEqual(pts["D85"]["value"], 160.0 * (230.0 / 160.0) ** 0.7)
        self.assertAlmostEqual(pts["W85"]["value"], 4.0 * 2.5 ** 0.7)

    def test_percent_lighter_than_a_limit(self):
        self.assertAlmostEqual(rm.percent_lighter_than(MASSES, 3.0), 15.0)  # 1 + 2 of 20
        self.assertAlmostEqual(rm.percent_lighter_than(MASSES, 3.5), 30.0)
        self.assertAlmostEqual(rm.percent_lighter_than(MASSES, 10.0), 50.0)
        self.assertAlmostEqual(rm.percent_lighter_than(MASSES, 10.5), 100.0)
        self.assertAlmostEqual(rm.percent_lighter_than(MASSES, 0.5), 0.0)


class Specification(unittest.TestCase):
    def write(self, text):
        f = tempfile.NamedTemporaryFile("w", suffix=".toml", delete=False)
        f.write(text)
        f.close()
        self.addCleanup(os.unlink, f.name)
        return f.name

    def test_control_points_pass_and_fail(self):
        path = self.write(
            'name = "test"\n'
            'mean_mass_kg = [3.0, 5.0]\n'
            '[[point]]\nlabel = "ELL"\nvalue = 1.5\nmax_percent_lighter = 5\n'
            '[[point]]\nlabel = "NLL"\nvalue = 3.5\nmax_percent_lighter = 10\n'
            '[[point]]\nlabel = "NUL"\nvalue = 9\nmin_percent_lighter = 70\n'
            '[[point]]\nlabel = "b"\nquantity = "b"\nvalue = 200\nmin_percent_lighter = 50\n')
        rows, passed = rm.check_spec(rm.load_spec(path), MASSES, B_MM)
        got = {r["label"]: (round(r["percent"], 6) if r["percent"] is not None else None, r["pass"])
               for r in rows}
        self.assertEqual(got["ELL"], (5.0, True))  # 1 kg of 20
        self.assertEqual(got["NLL"], (30.0, False))  # 1 + 2 + 3 kg
        self.assertEqual(got["NUL"], (50.0, False))
        self.assertEqual(got["b"], (50.0, True))  # all but the 230 mm stone
        self.assertEqual(got["mean mass"], (None, True))  # 4 kg
        self.assertFalse(passed)

    def test_ranges_by_count(self):
        # By count the five stones are 20 % each: sorted by b (100, 120, 150,
        # 160, 230 mm) D50 lies halfway between the 2nd (40 %) and the 3rd
        # (60 %): sqrt(120 x 150) = 134.16 mm; D100 is 230 mm. By mass W50
        # by count: sqrt(2 x 3) = 2.449 kg.
        path = self.write(
            'name = "fp"\n'
            '[[range]]\nlabel = "D50"\npercent = 50\nbasis = "count"\nquantity = "b"\n'
            'min = 130\nmax = 200\n'
            '[[range]]\nlabel = "D100"\npercent = 100\nquantity = "b"\nmin = 240\nmax = 380\n'
            '[[range]]\nlabel = "W50"\npercent = 50\nquantity = "mass"\nmin = 2\nmax = 3\n'
            '[[range]]\nlabel = "W10"\npercent = 10\nquantity = "mass"\nmin = 0.5\nmax = 3\n')
        rows, passed = rm.check_spec(rm.load_spec(path), MASSES, B_MM)
        got = {r["label"]: r for r in rows}
        self.assertAlmostEqual(got["D50"]["value"], math.sqrt(120.0 * 150.0))
        self.assertTrue(got["D50"]["pass"])
        self.assertAlmostEqual(got["D100"]["value"], 230.0)
        self.assertFalse(got["D100"]["pass"])
        self.assertAlmostEqual(got["W50"]["value"], math.sqrt(6.0))
        self.assertTrue(got["W50"]["pass"])
        # 10 % by count is below the first stone's 20 %: not determined, fails.
        self.assertIsNone(got["W10"]["value"])
        self.assertIn("too small", got["W10"]["why"])
        self.assertFalse(got["W10"]["pass"])
        self.assertFalse(passed)

    def test_bad_specification_is_named(self):
        for text, says in [
            ('name = "x"\n', "no [[point]] or [[range]]"),
            ('name = "x"\n[[range]]\npercent = 50\nmin = 3\nmax = 2\n', "min <= max"),
            ('name = "x"\n[[range]]\npercent = 0\nmin = 1\nmax = 2\n', "percent"),
            ('name = "x"\n[[range]]\nbasis = "volume"\npercent = 5\nmin = 1\nmax = 2\n',
             "basis"),
            ('[[point]]\nvalue = 1\nmax_percent_lighter = 5\n', "name"),
            ('name = "x"\n[[point]]\nvalue = -1\nmax_percent_lighter = 5\n', "positive"),
            ('name = "x"\n[[point]]\nvalue = 1\n', "min_percent_lighter"),
            ('name = "x"\n[[point]]\nquantity = "volume"\nvalue = 1\nmax_percent_lighter = 5\n',
             "quantity"),
            ('name = "x"\n[[point\n', "not valid TOML"),
        ]:
            with self.assertRaises(rm.ReportError) as cm:
                rm.load_spec(self.write(text))
            self.assertIn(says, str(cm.exception))
        with self.assertRaises(rm.ReportError) as cm:
            rm.load_spec("/no/such/spec.toml")
        self.assertIn("does not exist", str(cm.exception))

    def test_shipped_specifications_load(self):
        spec_dir = os.path.join(os.environ.get("AGGSCAN_SOURCE_DIR", "."), "scripts", "report",
                                "specs")
        names = sorted(n for n in os.listdir(spec_dir) if n.endswith(".toml"))
        self.assertTrue(names)
        for n in names:
            spec = rm.load_spec(os.path.join(spec_dir, n))
            self.assertTrue(spec.get("point") or spec.get("range"), n)
        self.assertIn("fp14-class1.toml", names)
        self.assertIn("en13383-lma10-60.toml", names)


class FlatAndElongated(unittest.TestCase):
    def test_shares_by_count_and_by_mass(self):
        # Boxes a, b, c (mm): c/a = 2.5, 3.5, 6.0, 1.5 and exactly 2.0 (not
        # greater than 2: not flat and elongated at 2:1).
        boxes = [(10, 20, 25), (10, 15, 35), (5, 20, 30), (20, 25, 30), (10, 10, 20)]
        ratios = [c / a for a, _, c in boxes]
        masses = [1.0, 2.0, 3.0, 4.0, 10.0]
        got = {r["ratio"]: r for r in rm.flat_elongated(ratios, masses)}
        self.assertEqual(got[2.0]["count"], 3)
        self.assertAlmostEqual(got[2.0]["by_count"], 60.0)
        self.assertAlmostEqual(got[2.0]["by_mass"], 30.0)  # 1 + 2 + 3 of 20
        self.assertAlmostEqual(got[3.0]["by_count"], 40.0)
        self.assertAlmostEqual(got[3.0]["by_mass"], 25.0)  # 2 + 3
        self.assertAlmostEqual(got[5.0]["by_count"], 20.0)
        self.assertAlmostEqual(got[5.0]["by_mass"], 15.0)  # 3
        self.assertIsNone(rm.flat_elongated(ratios, [])[0]["by_mass"])


class Statistics(unittest.TestCase):
    def test_stats_and_volume_errors(self):
        s = rm.stats([1.0, 2.0, 3.0, None])
        self.assertEqual(s["n"], 3)
        self.assertAlmostEqual(s["mean"], 2.0)
        self.assertAlmostEqual(s["std"], 1.0)
        self.assertAlmostEqual(s["cov"], 0.5)
        e = rm.volume_errors([102.0, 97.0], [100.0, 100.0])
        self.assertAlmostEqual(e["mpe"], -0.5)
        self.assertAlmostEqual(e["mape"], 2.5)


if __name__ == "__main__":
    unittest.main()
