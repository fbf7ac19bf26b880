"""`gridslam bench egomotion`: the table against a reference checkout, and the profile."""

from pathlib import Path

import pytest

from services.benchmarks import egomotion as bench
from services.common.errors import ConfigError

CHECKOUT = Path(__file__).resolve().parents[2]


def table_rows(text: str) -> list[list[str]]:
    return [[cell.strip() for cell in line.strip("|").split("|")] for line in text.splitlines() if line.startswith("| ") and "---" not in line]


def test_reference_checkout_is_timed_on_the_same_frames(capsys):
    """This checkout as its own reference: a second process times the same estimator on the
    same rendered frames (it checks their digest) and the table gains its times and the ratios."""
    assert bench.main(["--estimators", "scanline", "--frames", "3", "--repeats", "2", "--reference", str(CHECKOUT)]) == 0
    header, *rows = table_rows(capsys.readouterr().out)
    assert header[:5] == ["image", "estimator", "ms per frame (median)", "reference ms", "speed-up"]
    assert [row[:2] for row in rows] == [[label, "scanline"] for label, *_ in bench.SIZES]
    for row in rows:
        wall, reference, speed_up = (float(cell) for cell in row[2:5])
        assert wall > 0 and reference > 0
        assert speed_up == pytest.approx(reference / wall, rel=0.05, abs=0.01)


def test_reference_must_be_a_checkout(tmp_path):
    with pytest.raises(ConfigError, match="not a gridslam checkout"):
        bench.main(["--estimators", "passthrough", "--frames", "2", "--repeats", "1", "--reference", str(tmp_path)])


def test_profile_names_the_stereo_steps(capsys):
    assert bench.main(["--estimators", "stereo", "--frames", "3", "--profile", "--reference", str(CHECKOUT)]) == 0
    out = capsys.readouterr().out
    functions = {row[0] for row in table_rows(out)}
    for step in ("`stereo.estimate`", "`stereo._triangulate`", "`stereo._pose`", "`features.detect_bucketed`", "`<calcOpticalFlowPyrLK>`"):
        assert step in functions
    assert out.count("stereo at ") == out.count("stereo (reference) at ") == len(bench.SIZES)
