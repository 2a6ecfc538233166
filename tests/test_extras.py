"""The optional-extra policy of the test suite (tests/_extras.py): skip outside CI, fail in CI."""

from __future__ import annotations

import pytest
from _extras import require_extra

MISSING = "swiftjax_no_such_extra"


def test_missing_extra_skips_outside_ci(monkeypatch):
    monkeypatch.delenv("CI", raising=False)
    with pytest.raises(pytest.skip.Exception, match=f"{MISSING} is not installed"):
        require_extra(MISSING)


def test_missing_extra_fails_in_ci(monkeypatch):
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match=f"CI needs the test extra: {MISSING} is not installed"):
        require_extra(MISSING)


def test_present_extra_is_the_module(monkeypatch):
    monkeypatch.setenv("CI", "true")
    import json

    assert require_extra("json") is json
