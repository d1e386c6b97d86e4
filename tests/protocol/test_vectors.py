"""The golden vectors (protocol/vectors, SPEC §5) against the Python codec, and their coverage."""

from __future__ import annotations

import collections
import importlib.util
import re
from dataclasses import replace
from pathlib import Path

import pytest

from flytrack_host.protocol import MsgId
from flytrack_host.protocol.vectors import FAMILIES, Vector, check_vector, load_vectors

VECTOR_DIR = Path(__file__).resolve().parents[2] / "protocol" / "vectors"
VECTORS = load_vectors(VECTOR_DIR)
UDP_FAMILIES = [f for f, t in FAMILIES.items() if t is not None]


@pytest.mark.parametrize("v", VECTORS, ids=lambda v: f"{v.family}-{v.name}")
def test_vector(v: Vector) -> None:
    problem = check_vector(v)
    assert problem is None, problem


def _by(family: str, valid: bool) -> list[Vector]:
    return [v for v in VECTORS if v.family == family and v.valid == valid]


def test_every_family_present() -> None:
    assert {v.family for v in VECTORS} == set(FAMILIES)


@pytest.mark.parametrize("family", UDP_FAMILIES)
def test_udp_minimums(family: str) -> None:
    assert len(_by(family, True)) >= 3
    errors = collections.Counter(v.expect for v in _by(family, False))
    for name in ("TRUNCATED", "BAD_MAGIC", "BAD_VERSION", "UNKNOWN_TYPE", "LENGTH_MISMATCH"):
        assert errors[name] >= 1, name
    assert errors["TRUNCATED"] >= 3  # several cut points
    has_records = family in ("features", "image", "dvs_clusters", "dvs_wingbeat", "live_estimates")
    has_floats = family not in ("control_ack", "image")
    has_fields = family in ("features", "status", "control", "control_ack", "image", "dvs_clusters", "live_estimates")
    assert (errors["COUNT_OVERFLOW"] >= 2) == has_records
    assert (errors["NOT_FINITE"] >= 2) == has_floats
    assert (errors["BAD_FIELD"] >= 2) == has_fields


def test_features_specials() -> None:
    valid = _by("features", True)
    flags = [int(re.search(r"flags=(\d+)", v.expect).group(1)) for v in valid]
    assert any(f & 1 for f in flags), "a SPLIT vector"
    assert any(f & 2 and not f & 1 for f in flags), "a TRUNCATED vector"
    assert any("orientation=nan" in v.expect for v in valid)
    assert any("eccentricity=nan" in v.expect for v in valid)
    assert any("n_points=32" in v.expect for v in valid)
    names = {v.name for v in _by("features", False)}
    assert {"part_index_eq_part_count", "inf_orientation", "nan_x_dist"} <= names


def test_trigger_link_minimums() -> None:
    per_id = collections.Counter(int(re.match(r"msg_id=(\d+)", v.expect).group(1)) for v in _by("trigger_link", True))
    for mid in MsgId:
        assert per_id[int(mid)] >= 2, mid.name
    errors = collections.Counter(v.expect for v in _by("trigger_link", False))
    for name in ("BAD_COBS", "TRUNCATED", "BAD_CRC", "BAD_MAGIC", "BAD_VERSION", "UNKNOWN_TYPE",
                 "LENGTH_MISMATCH", "BAD_FIELD"):  # fmt: skip
        assert errors[name] >= 2, name


def test_dvs_words_minimums() -> None:
    assert len(_by("dvs_words", True)) >= 3
    errors = collections.Counter(v.expect for v in _by("dvs_words", False))
    assert errors["TRUNCATED"] >= 3 and errors["BAD_FIELD"] >= 3


def test_independent_vectors_present() -> None:
    assert sum(v.name.startswith("indep") for v in VECTORS) >= 5


def test_committed_vectors_are_what_the_generator_writes() -> None:
    spec = importlib.util.spec_from_file_location("ft_vector_generator", VECTOR_DIR / "generate.py")
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    files = gen.build()
    assert sorted(files) == sorted(f"{f}.tsv" for f in FAMILIES)
    for name, text in files.items():
        assert (VECTOR_DIR / name).read_text(encoding="ascii") == text, f"{name} is stale: run generate.py"


# The runner itself must be able to fail: corrupt vectors are reported.
def test_runner_reports_wrong_canonical_text() -> None:
    v = _by("features", True)[1]
    assert check_vector(replace(v, expect=v.expect.replace("camera_index=", "camera_index=1", 1))) is not None


def test_runner_reports_wrong_error_name() -> None:
    v = next(v for v in _by("status", False) if v.expect == "NOT_FINITE")
    assert "expected BAD_FIELD, got NOT_FINITE" in check_vector(replace(v, expect="BAD_FIELD"))


def test_runner_reports_accepted_invalid() -> None:
    v = _by("trigger_link", True)[0]
    assert "but it decoded" in check_vector(replace(v, valid=False, expect="BAD_CRC"))


def test_runner_reports_wrong_family() -> None:
    v = _by("status", True)[0]
    assert check_vector(replace(v, family="control")) is not None
