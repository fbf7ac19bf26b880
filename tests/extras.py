"""What the tests need beyond the core install: the declared extras (plots, ros, foxglove, test)
and the outside tools (Chromium, Node.js). Where one is missing its tests skip, and fail in CI
(CI=true, as `.ci/run` sets it), where everything declared is installed and part of what is tested."""

from __future__ import annotations

import importlib
import os

import pytest


def in_ci() -> bool:
    return os.environ.get("CI") == "true"


def unavailable(reason: str):
    """Skip the test (or the module, at import) for `reason`; in CI, fail it."""
    if in_ci():
        pytest.fail(f"{reason} (CI=true: every declared extra must be installed)", pytrace=False)
    pytest.skip(reason, allow_module_level=True)


def require(module: str, extra: str):
    """The module `module` of the extra `extra` (e.g. "test", "ros"); skips without it, fails in CI."""
    try:
        return importlib.import_module(module)
    except ImportError as error:
        unavailable(f"{module} ({extra} extra) is not installed: {error}")
