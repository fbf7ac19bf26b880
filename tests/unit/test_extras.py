"""A test of a missing declared extra skips, and fails in CI (tests/extras.py)."""

import pytest

from tests.extras import require


def test_a_missing_extra_skips_outside_ci_and_fails_in_ci(monkeypatch):
    monkeypatch.delenv("CI", raising=False)
    with pytest.raises(pytest.skip.Exception, match="gridslam_absent_module \\(test extra\\) is not installed"):
        require("gridslam_absent_module", "test")
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match="CI=true"):
        require("gridslam_absent_module", "test")
    assert require("json", "test").dumps([1]) == "[1]"
