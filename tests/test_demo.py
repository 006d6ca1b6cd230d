"""The demo's Table 8 comparison from a sweep table."""

import math

import pandas as pd

from jaxems.demo import table8_text


def test_table8_text_picks_the_mass_and_battery_and_shows_savings():
    rows = []
    for route in ("LongHaul", "UrbanDelivery"):
        for mass, batt in ((20000, 4), (30000, 4), (20000, 8)):
            for s, l100 in (("conventional", 30.0), ("baseline", 28.5), ("multilevel", 27.9)):
                sv = math.nan if s == "conventional" else 100 * (30.0 - l100) / 30.0
                rows.append(dict(route=route, mass_kg=mass, battery_MJ=batt, strategy=s,
                                 fuel_l_per_100km=l100 + (mass - 20000) / 1e4,
                                 saving_vs_conventional_pct=sv, status="ok"))
    text = table8_text(pd.DataFrame(rows))
    lines = text.splitlines()
    assert "20 t, 4 MJ" in lines[0]
    body = [ln for ln in lines if ln.startswith(("LongHaul", "UrbanDelivery"))]
    assert len(body) == 2
    for ln in body:
        assert "30.00" in ln and "28.50" in ln and "27.90" in ln  # the 20 t rows only
        assert "+5.0 %" in ln and "+7.0 %" in ln
