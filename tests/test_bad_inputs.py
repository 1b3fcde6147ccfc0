"""Every bad input of the corpus (``tests/bad_inputs.py``) is refused cleanly: exit status 2,
one line naming the problem, no traceback, no file lost, nothing in a file run. Plus the inputs
that look odd but are fine: a log with a byte-order mark or CRLF line ends, and a truncated
last line with ``--lenient``."""

from __future__ import annotations

import json

import pytest
from bad_inputs import TINY_LOG_JSON, corpus, make_shared, run_case

from pyro_slam import cli

PLACEHOLDER = {"good": "good.npz", "run": "run", "log": "good.clf"}
NAMES = [c.name for c in corpus(PLACEHOLDER)]


@pytest.fixture(scope="module")
def shared(tmp_path_factory):
    return make_shared(tmp_path_factory.mktemp("shared"))


def test_the_corpus_covers_at_least_150_distinct_bad_inputs():
    assert len(NAMES) >= 150 and len(set(NAMES)) == len(NAMES)


@pytest.mark.parametrize("name", NAMES)
def test_bad_input_is_refused_cleanly(name, shared, tmp_path):
    case = next(c for c in corpus(shared) if c.name == name)
    r = run_case(case, tmp_path)
    assert not r["traceback"], r["traceback"]
    assert r["rc"] == 2, (r["rc"], r["message"])
    assert r["one_line"], r["message"]
    assert r["names_it"], (case.expect, r["message"])
    assert not r["lost"], r["lost"]
    assert not r["executed"]


def _log(path, lines, newline="\n", bom=False):
    text = newline.join(lines) + newline
    path.write_bytes((b"\xef\xbb\xbf" if bom else b"") + text.encode())
    return path


def _flaser(i):
    nums = " ".join(str(v) for v in [1.0 + 0.1 * i] * 8 + [0.1 * i, 0, 0] * 2)
    return f"FLASER 8 {nums} {float(i)} host {float(i)}"


@pytest.mark.parametrize("newline,bom", [("\n", True), ("\r\n", False), ("\r\n", True)])
def test_byte_order_mark_and_crlf_keep_every_scan(tmp_path, newline, bom):
    log = _log(tmp_path / "l.clf", [_flaser(i) for i in range(6)], newline, bom)
    out = tmp_path / "o"
    assert cli.main(["slam", str(log), "--out", str(out), "--config", TINY_LOG_JSON]) == 0
    assert json.loads((out / "metrics.json").read_text())["steps"] == 6


def test_lenient_counts_and_lists_what_it_skipped(tmp_path, capsys):
    """``--lenient`` skips a truncated line and a corrupt one, says so in one line on stderr
    and counts and lists them in ``metrics.json``."""
    lines = [_flaser(i) for i in range(6)]
    lines.insert(3, "FLASER 8 abc")
    log = _log(tmp_path / "l.clf", lines + ["FLASER 8 1.0 1."])
    args = ["slam", str(log), "--config", TINY_LOG_JSON]
    assert cli.main([*args, "--out", str(tmp_path / "strict")]) == 2
    assert "l.clf:4" in capsys.readouterr().err
    assert cli.main([*args, "--out", str(tmp_path / "lenient"), "--lenient"]) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if "skipped" in line]
    assert len(err) == 1 and "skipped 2 malformed line(s)" in err[0] and "l.clf:4" in err[0]
    report = json.loads((tmp_path / "lenient" / "metrics.json").read_text())
    assert report["steps"] == 6 and report["skipped_lines"] == 2
    assert [r.split(": ")[0].rsplit(":", 1)[1] for r in report["skip_reasons"]] == ["4", "8"]


def test_a_metric_undefined_for_a_short_log_is_null_with_the_reason(tmp_path):
    """Six scans: no two are far enough apart in time to score each other's map, so scan
    consistency is ``null`` with the reason, never NaN nor a capped 1.0."""
    log = _log(tmp_path / "l.clf", [_flaser(i) for i in range(6)])
    out = tmp_path / "o"
    assert cli.main(["slam", str(log), "--out", str(out), "--config", TINY_LOG_JSON]) == 0
    text = (out / "metrics.json").read_text()
    assert "NaN" not in text
    for path in ("slam", "path_integration"):
        c = json.loads(text)["scan_consistency"][path]
        assert c["mean"] is None and c["median"] is None and "too short" in c["reason"]
