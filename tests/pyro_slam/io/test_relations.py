"""Kümmerle et al. relation error on trajectories with known, analytic error."""

from __future__ import annotations

import numpy as np
import pytest

from pyro_slam.io import (
    ParseError,
    read_carmen,
    read_relations,
    relation_error,
    relations_from_reference,
    write_relations,
)


def straight(T, step, heading=0.0):
    x = np.arange(T) * step
    return np.column_stack([x * np.cos(heading), x * np.sin(heading), np.full(T, heading)])


def test_constant_scale_drift_gives_analytic_translational_error():
    T, eps, ts = 50, 0.02, np.arange(50) * 0.5
    ref = straight(T, 1.0, heading=0.7)
    est = straight(T, 1.0 + eps, heading=0.7)  # every step eps too long
    consecutive = relations_from_reference(ts, ref)
    err = relation_error(ts, est, consecutive)
    assert err["trans_mean"] == pytest.approx(eps) and err["trans_std"] == pytest.approx(
        0, abs=1e-12
    )
    assert err["rot_mean_deg"] == pytest.approx(0, abs=1e-9)
    assert err["n_used"] == T - 1 and err["n_skipped"] == 0
    rand = relations_from_reference(ts, ref, consecutive=False, n_random=300, seed=1)
    steps = (rand[:, 1] - rand[:, 0]) / 0.5  # j - i
    err = relation_error(ts, est, rand)
    assert err["trans_mean"] == pytest.approx(eps * steps.mean())
    assert err["trans_std"] == pytest.approx(eps * steps.std())


def test_constant_heading_drift_gives_analytic_rotational_error():
    T, delta, ts = 30, np.radians(0.5), np.arange(30, dtype=float)
    ref = np.column_stack([np.zeros(T), np.zeros(T), np.zeros(T)])
    est = ref.copy()
    est[:, 2] = np.arange(T) * delta  # turning in place: no translational error
    rel = relations_from_reference(ts, ref, n_random=40, max_steps=5)
    err = relation_error(ts, est, rel)
    steps = rel[:, 1] - rel[:, 0]
    assert err["rot_mean_deg"] == pytest.approx(0.5 * steps.mean())
    assert err["trans_mean"] == pytest.approx(0, abs=1e-12)
    assert (steps >= 1).all() and (steps <= 5).all()


def test_relations_beyond_max_dt_are_skipped_and_duplicates_dropped():
    ts = np.array([0.0, 1.0, 1.0, 2.0])
    ref = straight(4, 1.0)
    rel = relations_from_reference(ts, ref)
    assert rel[:, :2].tolist() == []  # every consecutive pair touches the shared time 1.0
    rel = np.array([[0.0, 2.0, 2.0, 0, 0, 0, 0, 0], [0.0, 2.5, 2.0, 0, 0, 0, 0, 0]])  # x=3 really
    err = relation_error(ts, ref, rel, max_dt=0.1)
    assert err["n_used"] == 1 and err["n_skipped"] == 1 and err["trans_mean"] == pytest.approx(1)
    none = relation_error(ts, ref, rel[1:], max_dt=0.1)
    assert none["n_used"] == 0 and np.isnan(none["trans_mean"])


def test_relation_file_round_trip_and_errors(tmp_path):
    rel = relations_from_reference(np.arange(5.0), straight(5, 0.3, 0.2), n_random=3)
    path = write_relations(rel, tmp_path / "rel.txt")
    np.testing.assert_array_equal(read_relations(path), rel)
    bad = tmp_path / "bad.txt"
    bad.write_text("# t1 t2 x y z roll pitch yaw\n0 1 0 0 0 0 0 0\n\n1 2 0.5 0 0 0 0\n")
    with pytest.raises(ParseError, match=r"bad.txt:4: expected 8 fields"):
        read_relations(bad)
    bad.write_text("0 1 0 0 0 0 0 zero\n")
    with pytest.raises(ParseError, match=r"bad.txt:1: non-numeric value 'zero'"):
        read_relations(bad)


def test_relations_file_with_a_byte_order_mark_or_a_folder(tmp_path):
    """A relations file saved with a byte-order mark reads as without one; a folder given as
    the file (or as a CARMEN log) is a ParseError naming it, not a bare OSError."""
    marked = tmp_path / "marked.relations"
    marked.write_text("# t1 t2 x y z roll pitch yaw\n0 1 0.5 0 0 0 0 0.1\n", encoding="utf-8-sig")
    np.testing.assert_allclose(read_relations(marked), [[0, 1, 0.5, 0, 0, 0, 0, 0.1]])
    for read, what in ((read_relations, "relations file"), (read_carmen, "CARMEN log")):
        with pytest.raises(ParseError, match=f"{tmp_path}: is a folder, not a {what}"):
            read(tmp_path)
