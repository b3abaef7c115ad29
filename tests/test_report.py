"""The page's number formatting: ``report.num``."""

import math

from pinnhjb import report


def test_num_formats_rounding_noise_floors_and_missing_numbers():
    assert report.num(1.23456e-3) == "1.23e-03"
    assert report.num(0.5, ".2f") == "0.50"
    assert report.num(-1e-15, ".1e") == "0.0e+00"  # rounding noise: no sign, no digits
    assert report.num(3e-9, ".1e", floor=1e-6) == "< 1e-6"
    assert report.num(math.nan) == "nan" and report.num(math.inf, ".1e") == "inf"
    assert report.num(None) == report.num(None, ".1e") == "–"  # a number the run did not measure
    assert report.num({"a": 1.0}.get("b"), "g") == "–"
