"""A corpus of bad inputs for the ``pyro-slam`` command line, generated (nothing binary is
committed) and run in-process.

Each case writes its files into a fresh folder, runs ``pyro_slam.cli.main(argv)`` there and
expects a refusal: exit status 2, one line on stderr that starts ``pyro-slam CMD: error:``
and, where the case says so, names the file, line, field or option; no traceback; every file
that existed before is unchanged afterwards; and nothing in a file ran (a malicious pickle
would create ``PWNED``).

    python tests/bad_inputs.py          # run the whole corpus, print the counts as JSON

``tests/test_bad_inputs.py`` runs every case in the test suite.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import pickle
import sys
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from pyro_slam.pretrained import PRETRAINED as PRETRAINED_DIR

TINY = {"filter": {"particles": 16}, "training": {"particles": 4, "chunks": 2}}
TINY_JSON = json.dumps(TINY)
TINY_LOG_JSON = json.dumps({"filter": TINY["filter"]})  # (a real log's preset takes no SVI steps)
MARKER = "PWNED"


@dataclass
class Case:
    """One bad input: ``setup(folder)`` writes its files, ``argv`` runs in that folder, and
    stderr must contain ``expect`` (a string or one of several)."""

    name: str
    argv: list[str]
    expect: str | tuple[str, ...] = ""
    setup: Callable[[Path], None] | None = None
    needs: tuple[str, ...] = field(default=())  # shared fixtures: "good", "run", "log"


class Evil:
    """Pickles to a call that would create the marker file."""

    def __reduce__(self):
        return (os.system, (f"touch {MARKER}",))


# ------------------------------------------------------------------------------ shared files
def make_shared(root: Path) -> dict[str, Path]:
    """A valid simulated data set, a finished tiny run (with its checkpoint) and a small valid
    CARMEN log, shared (read-only) by the cases."""
    from pyro_slam import cli

    root.mkdir(parents=True, exist_ok=True)
    good = root / "good.npz"
    if not good.is_file():
        args = ["simulate", "--maze", "simple-small", "--steps", "24", "--seed", "3"]
        with contextlib.redirect_stdout(io.StringIO()):
            assert cli.main([*args, "--out", str(good), "--no-plot"]) == 0
    run = root / "run"
    if not (run / "checkpoint.pt").is_file():
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            argv = ["slam", str(good), "--out", str(run), "--config", TINY_JSON]
            assert cli.main(argv) == 0
    log = root / "good.clf"
    lines = [_flaser([1.0 + 0.1 * i] * 8, (0.1 * i, 0.0, 0.0), t=float(i)) for i in range(6)]
    log.write_text("\n".join(lines) + "\n")
    return {"good": good, "run": run, "log": log}


def _flaser(ranges, pose=(0.0, 0.0, 0.0), t=0.0) -> str:
    nums = " ".join(str(v) for v in [*ranges, *pose, *pose])
    return f"FLASER {len(ranges)} {nums} {t} host {t}"


# ------------------------------------------------------------------------------ case makers
def _npz(shared, name: str, change: Callable[[dict], dict]):
    """A case whose data set is the good one with ``change`` applied to its arrays."""

    def setup(d: Path):
        arrays = dict(np.load(shared["good"]))
        np.savez(d / name, **change(arrays))

    return setup


def _bytes(name: str, data: bytes | Callable[[], bytes]):
    def setup(d: Path):
        (d / name).write_bytes(data() if callable(data) else data)

    return setup


def _text(name: str, text: str):
    def setup(d: Path):
        (d / name).write_text(text)

    return setup


def _from_good(shared, name: str, mutate: Callable[[bytes], bytes]):
    def setup(d: Path):
        (d / name).write_bytes(mutate(shared["good"].read_bytes()))

    return setup


def _flip(data: bytes, at: int) -> bytes:
    b = bytearray(data)
    b[at % len(b)] ^= 0xFF
    return bytes(b)


def _copy_run(shared, ckpt: bytes | Callable[[bytes], bytes] | None = None):
    """The finished run's folder copied in, its checkpoint replaced (or changed) by ``ckpt``."""

    def setup(d: Path):
        out = d / "run"
        out.mkdir()
        for p in shared["run"].iterdir():
            (out / p.name).write_bytes(p.read_bytes())
        if ckpt is not None:
            old = (out / "checkpoint.pt").read_bytes()
            (out / "checkpoint.pt").write_bytes(ckpt(old) if callable(ckpt) else ckpt)

    return setup


def _rewritten(data: bytes, change) -> bytes:
    """A checkpoint's bytes with ``change`` applied to its contents, its digest made to fit
    (an intact file of the right format whose contents are wrong)."""
    from pyro_slam.slam import checkpoint

    head = len(checkpoint.MAGIC) + 65
    d = torch.load(io.BytesIO(data[head:]), weights_only=True)
    payload = _torch_bytes(change(d))
    digest = hashlib.sha256(payload).hexdigest().encode()
    return checkpoint.MAGIC + digest + b"\n" + payload


def _torch_bytes(obj) -> bytes:
    buf = io.BytesIO()
    torch.save(obj, buf)
    return buf.getvalue()


def _forged_header(arrays: dict) -> bytes:
    """The good data set with an observations header declaring a 1e7 x 1e7 float64 array."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for k, v in arrays.items():
            if k == "observations":
                hdr = io.BytesIO()
                np.lib.format.write_array_header_1_0(
                    hdr, {"descr": "<f8", "fortran_order": False, "shape": (10**7, 10**7)}
                )
                z.writestr("observations.npy", hdr.getvalue() + b"\0" * 64)
            else:
                m = io.BytesIO()
                np.save(m, v)
                z.writestr(k + ".npy", m.getvalue())
    return buf.getvalue()


def _zip_bomb(arrays: dict) -> bytes:
    """The good data set plus a member that unpacks to 1.2 GB of zeros (about 1 MB packed)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as z:
        for k, v in arrays.items():
            m = io.BytesIO()
            np.save(m, v)
            z.writestr(k + ".npy", m.getvalue())
        hdr = io.BytesIO()
        np.lib.format.write_array_header_1_0(
            hdr, {"descr": "<f8", "fortran_order": False, "shape": (150_000_000,)}
        )
        with z.open("extra.npy", "w", force_zip64=True) as m:
            m.write(hdr.getvalue())
            zeros = b"\0" * (1 << 24)
            for _ in range(72):
                m.write(zeros)
    return buf.getvalue()


# ------------------------------------------------------------------------------ the corpus
def option_cases() -> list[Case]:
    """Command-line options out of range or of the wrong type (argparse, before any work)."""
    s = ["slam", "good.npz", "--out", "o"]
    sim = ["simulate", "--maze", "simple-small", "--out", "t.npz"]
    cases = []
    for opt, bad in [
        ("--steps", "-1"),
        ("--steps", "abc"),
        ("--steps", "1.5"),
        ("--seed", "-3"),
        ("--seed", "x"),
        ("--odometry-noise", "-1"),
        ("--odometry-noise", "0"),
        ("--odometry-noise", "nan"),
        ("--odometry-noise", "inf"),
        ("--mode", "both"),
        ("--preset", "nope"),
        ("--seed", str(2**40)),
    ]:
        cases.append(Case(f"slam {opt} {bad}", [*s, opt, bad], opt))
    for opt, bad in [
        ("--steps", "0"),
        ("--steps", "-5"),
        ("--steps", "1e9x"),
        ("--seed", "-1"),
        ("--distractors", "-2"),
        ("--maze", "huge"),
        ("--steps", "1000000000"),
        ("--seed", str(2**32)),
        ("--distractors", "10000000"),
    ]:
        cases.append(Case(f"simulate {opt} {bad}", [*sim, opt, bad], opt))
    pre = ["pretrain", "--out", "p"]
    for opt, bad in [
        ("--emission-steps", "-1"),
        ("--emission-steps", "0"),
        ("--steps", "-4"),
        ("--transition-epochs", "0"),
        ("--seed", "-1"),
    ]:
        cases.append(Case(f"pretrain {opt} {bad}", [*pre, opt, bad], opt))
    for opt, bad in [
        ("--steps", "0"),
        ("--seed", "-1"),
        ("--mode", "sideways"),
        ("--preset", "best"),
        ("--steps", "1000000000"),
        ("--seed", str(2**32)),
    ]:
        cases.append(Case(f"demo {opt} {bad}", ["demo", "--out", "d", opt, bad], opt))
    nav = ["navigate", "--out", "n.png"]
    for opt, bad in [
        ("--max-expansions", "0"),
        ("--fit-steps", "-1"),
        ("--n-world", "5"),
        ("--maze-seed", "-1"),
        ("--maze-seed", str(2**32)),
        ("--traversal-steps", "0"),
        ("--traversal-steps", "1000000000"),
        ("--inverse-steps", "0"),
        ("--planner", "oracle"),
        ("--map", "none"),
    ]:
        cases.append(Case(f"navigate {opt} {bad}", [*nav, opt, bad], opt))
    cases.append(Case("navigate --start nan", [*nav, "--start", "nan", "0", "0"], "--start"))
    cases.append(Case("navigate --goal inf", [*nav, "--goal", "inf", "0"], "--goal"))
    cases.append(Case("no command", [], "command"))
    cases.append(Case("unknown command", ["fly"], "fly"))
    return cases


def config_cases(shared) -> list[Case]:
    """``--config`` JSON: syntax, unknown fields, wrong types, out-of-range values, and values
    that would not fit in memory, each naming the field."""
    bad = [
        ("filter", "particles", -5),
        ("filter", "particles", "abc"),
        ("filter", "particles", None),
        ("filter", "particles", 2.5),
        ("filter", "particles", 0),
        ("filter", "particles", True),
        ("filter", "particles", 10**9),
        ("filter", "sigma", 0),
        ("filter", "sigma", -1),
        ("filter", "sigma", "x"),
        ("filter", "outlier_prob", 1),
        ("filter", "outlier_prob", -0.1),
        ("filter", "weighting", "predictive"),
        ("filter", "weighting", 3),
        ("emission", "resolution", 0),
        ("emission", "resolution", -0.1),
        ("emission", "resolution", 1e-5),
        ("emission", "resolution", 1e308),
        ("emission", "kind", "laser"),
        ("emission", "margin", -1),
        ("emission", "sigma", 0),
        ("emission", "sigma", None),
        ("emission", "insert", {"gap": 0}),
        ("emission", "insert", {"scale": -1}),
        ("emission", "insert", {"occupancy": "high"}),
        ("transition", "sigma", [-1, 0, 0]),
        ("transition", "sigma", [1, 1]),
        ("transition", "scale", [0, 1, 1]),
        ("transition", "scale", "big"),
        ("transition", "scale_trusted", [1, 1, None]),
        ("transition", "kind", "neural"),
        ("transition", "sigma", [0.1, 0.1, 0.1]),  # the (default) learned transition ignores it
        ("training", "particles", 0),
        ("training", "chunks", -1),
        ("training", "chunk_length", 0),
        ("training", "lr", 0),
        ("training", "lr", -0.02),
        ("training", "every", -1),
        ("training", "objective", "tempered"),
        ("training", "particles", 10**6),
        ("offline", "rounds", -1),
        ("offline", "svi_steps", 2.5),
        ("offline", "estimate", "both"),
        ("heading", "sigma", 0),
        ("heading", "support", 1),
        ("heading", "support", "many"),
    ]
    cases = []
    s = ["slam", str(shared["good"]), "--out", "o"]
    for comp, name, value in bad:
        cfg = json.dumps({comp: {name: value}})
        cases.append(Case(f"config {comp}.{name}={value!r}", [*s, "--config", cfg], f"{comp}."))
    cases.append(
        Case(
            "config mlp with insertion",
            [*s, "--config", json.dumps({"emission": {"kind": "mlp", "insert": {}}})],
            "emission.insert",
        )
    )
    for name, text, expect in [
        ("config unknown top field", '{"nope": 1}', "nope"),
        ("config unknown nested field", '{"filter": {"particle": 3}}', "filter.particle"),
        ("config unknown fields", '{"a": 1, "b": 2, "c": 3}', "a, b, c"),
        ("config not json", "{filter: 3}", "JSON"),
        ("config a list", "[1, 2]", "JSON object"),
        ("config a number", "3", "JSON object"),
        ("config component not an object", '{"filter": 5}', "filter"),
        ("config beam_stride 0", '{"beam_stride": 0}', "beam_stride"),
        ("config a missing file", "missing.json", "missing.json"),
        ("config a very long non-JSON string", "x" * 5000, "--config"),
        ("config range_clip negative", '{"range_clip": -3}', "range_clip"),
        ("config range_clip beyond the sensor", '{"range_clip": 1e308}', "range_clip"),
        ("config beam_stride beyond the beams", '{"beam_stride": 1000}', "beam_stride"),
    ]:
        cases.append(Case(name, [*s, "--config", text], expect))
    return cases


def _o(arrays: dict) -> np.ndarray:
    return arrays["observations"]


def _eye(arrays: dict) -> np.ndarray:
    return np.eye(*_o(arrays).shape) > 0


def data_cases(shared) -> list[Case]:
    """Data sets (.npz) that are corrupt, inconsistent, implausible or too large."""
    changes = {
        "nan observation": lambda a: {**a, "observations": np.where(_eye(a), np.nan, _o(a))},
        "inf observation": lambda a: {**a, "observations": np.full_like(_o(a), np.inf)},
        "negative range": lambda a: {**a, "observations": -_o(a)},
        "all at max range": lambda a: {**a, "observations": np.full_like(_o(a), a["max_range"])},
        "all zero with zero range": lambda a: {**a, "observations": _o(a) * 0, "max_range": 0.0},
        "wrong beam count": lambda a: {**a, "observations": _o(a)[:, :7]},
        "controls length": lambda a: {**a, "controls": a["controls"][:-3]},
        "poses length": lambda a: {**a, "poses": a["poses"][:5]},
        "string dtype": lambda a: {**a, "observations": _o(a).astype(str)},
        "empty sequence": lambda a: {**a, "observations": _o(a)[:0], "controls": a["controls"][:0]},
        "missing controls": lambda a: {k: v for k, v in a.items() if k != "controls"},
        "missing max_range": lambda a: {k: v for k, v in a.items() if k != "max_range"},
        "wall at 1e6": lambda a: {**a, "walls": np.concatenate([a["walls"], [[0, 0, 2e6, 0]]])},
        "pose at 1e9": lambda a: {**a, "poses": a["poses"] + 1e9},
        "max_range 1e300": lambda a: {**a, "max_range": np.float64(1e300)},
        "max_range negative": lambda a: {**a, "max_range": np.float64(-1.0)},
        "max_range array": lambda a: {**a, "max_range": np.ones(3)},
        "walls wrong width": lambda a: {**a, "walls": a["walls"][:, :3]},
        "beam angles wrong length": lambda a: {**a, "beam_angles": a["beam_angles"][:3]},
        "beam angles huge": lambda a: {**a, "beam_angles": a["beam_angles"] * 1e3},
        "mask wrong dtype": lambda a: {**a, "obs_mask": np.ones_like(_o(a))},
        "mask all false": lambda a: {**a, "obs_mask": np.zeros(_o(a).shape, bool)},
        "timestamps decrease": lambda a: {**a, "timestamps": np.arange(len(_o(a)), 0, -1.0)},
        "timestamps wrong length": lambda a: {**a, "timestamps": np.arange(3.0)},
        "images out of range": lambda a: {**a, "images": np.full((len(_o(a)), 2, 3), 2.0)},
        "images wrong length": lambda a: {**a, "images": np.zeros((2, 2, 3))},
        "metadata not json": lambda a: {**a, "metadata": np.array("{not json")},
        "controls nan": lambda a: {**a, "controls": a["controls"] * np.nan},
        "format version from the future": lambda a: {**a, "format_version": np.array(99)},
    }
    cases = [
        Case(
            f"data {k}",
            ["slam", k.replace(" ", "_") + ".npz", "--out", "o"],
            k.replace(" ", "_") + ".npz",
            _npz(shared, k.replace(" ", "_") + ".npz", f),
        )
        for k, f in changes.items()
    ]
    raw = [
        ("empty file", _bytes("d.npz", b"")),
        ("not a zip", _bytes("d.npz", b"not a zip file at all")),
        ("truncated", _from_good(shared, "d.npz", lambda b: b[: len(b) // 2])),
        ("truncated end", _from_good(shared, "d.npz", lambda b: b[:-30])),
        ("bit flip in data", _from_good(shared, "d.npz", lambda b: _flip(b, len(b) // 3))),
        (
            "bit flip in a member's checksum",
            _from_good(shared, "d.npz", lambda b: _flip(b, b.find(b"PK\x01\x02") + 16)),
        ),
        ("bit flip near end", _from_good(shared, "d.npz", lambda b: _flip(b, -10))),
        ("a bare npy", lambda d: np.save(d / "d.npz", np.zeros(3))),
        (
            "object array (pickle)",
            lambda d: np.savez(d / "d.npz", observations=np.array([Evil()], dtype=object)),
        ),
        (
            "forged array header",
            lambda d: (d / "d.npz").write_bytes(_forged_header(dict(np.load(shared["good"])))),
        ),
        ("zip bomb", lambda d: (d / "d.npz").write_bytes(_zip_bomb(dict(np.load(shared["good"]))))),
        ("a directory", lambda d: (d / "d.npz").mkdir()),
        ("missing file", None),
    ]
    cases += [Case(f"data {n}", ["slam", "d.npz", "--out", "o"], "d.npz", f) for n, f in raw]
    return cases


def log_cases(shared) -> list[Case]:
    """CARMEN logs that cannot be read or hold no usable data, naming the line."""
    ok = [_flaser([1.0 + 0.1 * i] * 8, (0.1 * i, 0.0, 0.0), t=float(i)) for i in range(6)]
    text = {
        "empty log": "",
        "only comments": "# nothing\n# here\n",
        "no scans": "ODOM 0 0 0 0 0 0 1 host 1\n",
        "wrong field count": "\n".join(ok[:2]) + "\nFLASER 8 1 2 3\n",
        "non numeric range": "\n".join(ok[:2] + [ok[2].replace(" 1.2 ", " abc ", 1)]) + "\n",
        "nan pose": "\n".join(ok[:2] + [_flaser([1.0] * 8, (float("nan"), 0, 0), 2.0)]) + "\n",
        "pose of 1e9": "\n".join(ok[:2] + [_flaser([1.0] * 8, (1e9, 0, 0), 2.0)]) + "\n",
        "readings change count": "\n".join(ok[:2] + [_flaser([1.0] * 5, t=2.0)]) + "\n",
        "zero readings": "\n".join(ok[:2]) + "\nFLASER 0 0 0 0 0 0 0 2 host 2\n",
        "negative count": "\n".join(ok[:2]) + "\nFLASER -3 1 1 1 0 0 0 0 0 0 2 host 2\n",
        "all ranges 1e300": "\n".join(_flaser([1e300] * 8, t=float(i)) for i in range(4)) + "\n",
        "all ranges zero": "\n".join(_flaser([0.0] * 8, t=float(i)) for i in range(4)) + "\n",
        "all ranges nan": "\n".join(_flaser([float("nan")] * 8, t=float(i)) for i in range(4)),
        "reversed timestamps": "\n".join(ok[::-1]) + "\n",
        "truncated last line": "\n".join(ok) + "\nFLASER 8 1.0 1.0 1.",
        "binary garbage": "\x00\x01\x02FLASER\xff\xfe\n" * 3,
        "odom wrong count": "\n".join(ok) + "\nODOM 1 2 3\n",
        "odom inf": "\n".join(ok) + "\nODOM 1 inf 3 0 0 0 9 host 9\n",
    }
    cases = [
        Case(f"log {k}", ["slam", "l.clf", "--out", "o"], "l.clf", _text("l.clf", v))
        for k, v in text.items()
    ]
    cases.append(
        Case(
            "log lenient on an npz",
            ["slam", str(shared["good"]), "--out", "o", "--lenient"],
            "--lenient",
        )
    )
    cases.append(
        Case(
            "log unknown type", ["slam", "l.txt", "--out", "o"], "l.txt", _text("l.txt", "hello\n")
        )
    )
    return cases


def resume_cases(shared) -> list[Case]:
    """``--resume`` with checkpoints that are damaged, unsafe or of another run."""
    good = str(shared["good"])
    r = ["slam", good, "--out", "run", "--config", TINY_JSON, "--resume"]
    ck = "checkpoint.pt"
    damaged = {
        "empty checkpoint": b"",
        "garbage checkpoint": b"\x00garbage" * 50,
        "truncated checkpoint": lambda b: b[: len(b) // 2],
        "checkpoint tail cut": lambda b: b[:-100],
        "bit-flipped checkpoint": lambda b: _flip(b, len(b) // 2),
        "bit-flipped checkpoint header": lambda b: _flip(b, 40),
        "malicious pickle": pickle.dumps(Evil()),
        "malicious torch.save": lambda _b: _torch_bytes({"format": 2, "x": Evil()}),
        "a plain dict": lambda _b: _torch_bytes({"a": 1}),
        "a tensor": lambda _b: _torch_bytes(torch.zeros(3)),
        "wrong format version": lambda _b: _torch_bytes({"format": 1, "fingerprint": {}}),
        "missing state": lambda b: _rewritten(b, lambda d: {k: d[k] for k in d if k != "state"}),
        "foreign but intact": lambda b: _rewritten(b, lambda d: {**d, "state": {"t": "x"}}),
        "unsafe but intact": lambda b: _rewritten(b, lambda d: {**d, "x": Evil()}),
    }
    cases = [Case(f"resume {n}", r, ck, _copy_run(shared, v)) for n, v in damaged.items()]
    cases += [
        Case("resume without a checkpoint", r, ck, lambda d: (d / "run").mkdir()),
        Case(
            "resume a checkpoint that is a folder",
            r,
            ck,
            lambda d: (d / "run" / ck).mkdir(parents=True),
        ),
        Case(
            "resume another traversal",
            ["slam", "other.npz", "--out", "run", "--config", TINY_JSON, "--resume"],
            "data set",
            lambda d: (_copy_run(shared)(d), _sim(d, 5)),
        ),
        Case(
            "resume a shorter traversal",
            [*r[:2], "--steps", "10", *r[2:]],
            "data set",
            _copy_run(shared),
        ),
        Case(
            "resume other config",
            ["slam", good, "--out", "run", "--config", '{"filter": {"particles": 8}}', "--resume"],
            "filter.particles",
            _copy_run(shared),
        ),
        Case("resume other seed", [*r, "--seed", "7"], "seed", _copy_run(shared)),
        Case("resume other preset", [*r, "--preset", "paper"], "emission.kind", _copy_run(shared)),
        Case("resume as offline", [*r, "--mode", "offline"], "online run", _copy_run(shared)),
        Case("a second run into a finished folder", r[:-1], "not empty", _copy_run(shared)),
        Case(
            "navigate a run with another maze's traversal",
            ["navigate", "--from", "run", "--traversal", "other.npz", "--out", "n.png"],
            "'walls'",
            lambda d: (_copy_run(shared)(d), _sim(d, 5)),
        ),
        Case(
            "demo into a finished folder",
            ["demo", "--out", "run", "--steps", "20"],
            "not empty",
            _copy_run(shared),
        ),
    ]
    return cases


def _sim(d: Path, seed: int) -> None:
    from pyro_slam import cli

    argv = ["simulate", "--maze", "simple-small", "--steps", "24", "--seed", str(seed)]
    with contextlib.redirect_stdout(io.StringIO()):
        cli.main([*argv, "--out", str(d / "other.npz"), "--no-plot"])


def network_cases(shared) -> list[Case]:
    """``--emission`` / ``--transition`` files that are not the right network."""
    from pyro_slam import pretrained

    em_file = pretrained.PRETRAINED / pretrained.EMISSION_FILE
    tr_file = pretrained.PRETRAINED / pretrained.TRANSITION_FILE
    s = ["slam", str(shared["good"]), "--out", "o", "--preset", "paper"]
    files = {
        "garbage": b"garbage" * 10,
        "empty": b"",
        "malicious pickle": pickle.dumps(Evil()),
        "malicious torch.save": _torch_bytes({"state_dict": Evil()}),
        "a tensor": _torch_bytes(torch.ones(4)),
        "a plain dict": _torch_bytes({"a": 1}),
    }
    cases = []
    for n, data in files.items():
        cases.append(
            Case(f"emission {n}", [*s, "--emission", "n.pt"], "n.pt", _bytes("n.pt", data))
        )
        cases.append(
            Case(f"transition {n}", [*s, "--transition", "n.pt"], "n.pt", _bytes("n.pt", data))
        )
    cases += [
        Case("emission is the transition file", [*s, "--emission", str(tr_file)], "emission"),
        Case("transition is the emission file", [*s, "--transition", str(em_file)], "transition"),
        Case("emission missing", [*s, "--emission", "missing.pt"], "missing.pt"),
        Case(
            "emission for the ray-cast preset",
            ["slam", str(shared["good"]), "--out", "o", "--emission", str(em_file)],
            "--emission",
        ),
        Case(
            "emission for other beams",
            [*s, "--emission", "wide.pt"],
            "wide.pt",
            lambda d: (d / "wide.pt").write_bytes(
                _torch_bytes({"state_dict": {}, "meta": {"n_world": 64, "map_dim": 10}})
            ),
        ),
    ]
    return cases


def output_cases(shared) -> list[Case]:
    """Output paths that are files, folders or cannot be created; nothing is lost."""
    good = str(shared["good"])
    sim = ["simulate", "--maze", "simple-small", "--steps", "20"]
    return [
        Case("slam --out is a file", ["slam", good, "--out", "f"], "--out", _text("f", "keep")),
        Case(
            "slam --out under a file", ["slam", good, "--out", "f/sub"], "--out", _text("f", "keep")
        ),
        Case(
            "slam --out not empty",
            ["slam", good, "--out", "o"],
            "not empty",
            lambda d: (d / "o").mkdir() or (d / "o" / "notes.txt").write_text("mine"),
        ),
        Case(
            "simulate --plot under a file",
            [*sim, "--out", "keep.npz", "--plot", "f/p.png"],
            "--plot",
            lambda d: (_text("f", "x")(d), _copy_good(shared, d)),
        ),
        Case(
            "simulate --plot is a folder",
            [*sim, "--out", "keep.npz", "--plot", "pd"],
            "--plot",
            lambda d: ((d / "pd").mkdir(), _copy_good(shared, d)),
        ),
        Case(
            "simulate --out is a folder",
            [*sim, "--out", "od"],
            "--out",
            lambda d: (d / "od").mkdir(),
        ),
        Case(
            "simulate --out under a file", [*sim, "--out", "f/t.npz"], "--out", _text("f", "keep")
        ),
        Case(
            "navigate --out under a file",
            ["navigate", "--out", "f/n.png", "--traversal-steps", "10"],
            "--out",
            _text("f", "keep"),
        ),
        Case(
            "pretrain --out is a file",
            ["pretrain", "--out", "f", "--steps", "10"],
            "--out",
            _text("f", "keep"),
        ),
        Case(
            "demo --out is a file",
            ["demo", "--out", "f", "--steps", "10"],
            "--out",
            _text("f", "keep"),
        ),
    ]


def _copy_good(shared, d: Path) -> None:
    (d / "keep.npz").write_bytes(shared["good"].read_bytes())


def _ros2_bag(path: Path, ranges: np.ndarray, topics=("/scan",), back: int | None = None) -> None:
    """A ROS 2 bag of LaserScans ``ranges [T, B]`` (10 Hz, 0.2 rad apart, range_max 8) on
    ``topics`` and an Odometry stream moving 0.1 m per scan; scan ``back``'s stamp 1 s back."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    ty, gm = store.types, "geometry_msgs/msg/"
    scan_type, odom_type = "sensor_msgs/msg/LaserScan", "nav_msgs/msg/Odometry"
    with Writer2(path, version=9) as w:
        conns = {t: w.add_connection(t, scan_type, typestore=store) for t in topics}
        conns["/odom"] = w.add_connection("/odom", odom_type, typestore=store)
        for k, r in enumerate(np.asarray(ranges, dtype=np.float32)):
            t = 100.0 + 0.1 * k
            s = t - (k == back)
            stamp = ty["builtin_interfaces/msg/Time"](sec=int(s), nanosec=int(s % 1 * 1e9))
            header = ty["std_msgs/msg/Header"](stamp=stamp, frame_id="laser")
            scan = ty[scan_type](
                header=header,
                angle_min=-0.2 * (len(r) // 2),
                angle_max=0.2 * (len(r) // 2),
                angle_increment=0.2,
                time_increment=0.0,
                scan_time=0.1,
                range_min=0.05,
                range_max=8.0,
                ranges=r,
                intensities=np.zeros(0, np.float32),
            )
            for topic in topics:
                w.write(conns[topic], int(t * 1e9), store.serialize_cdr(scan, scan_type))
            pose = ty[gm + "Pose"](
                position=ty[gm + "Point"](x=0.1 * k, y=0.0, z=0.0),
                orientation=ty[gm + "Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            )
            zero = ty[gm + "Vector3"](x=0.0, y=0.0, z=0.0)
            odom = ty[odom_type](
                header=header,
                child_frame_id="base_link",
                pose=ty[gm + "PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
                twist=ty[gm + "TwistWithCovariance"](
                    twist=ty[gm + "Twist"](linear=zero, angular=zero), covariance=np.zeros(36)
                ),
            )
            w.write(conns["/odom"], int(t * 1e9), store.serialize_cdr(odom, odom_type))


def _walls_away(a: dict) -> dict:
    w = a["walls"].copy()
    w[2, 1] = 1e6
    return {**a, "walls": w}


def _pose_away(a: dict) -> dict:
    p = a["poses"].copy()
    p[5, 0] = 1e6
    return {**a, "poses": p}


def _control_away(a: dict) -> dict:
    c = a["controls"].copy()
    c[3, 1] = 1e6  # the loader's magnitude limit
    return {**a, "controls": c}


def _path_too_wide(a: dict) -> dict:
    """Turns of 90 degrees and steps of 500 units: each step plausible, the path's square too
    wide for the exported map."""
    c = a["controls"].copy()
    c[:, 0], c[:, 1] = np.pi / 2, 500.0
    return {**a, "controls": c}


def _metadata(a: dict, **changes) -> dict:
    meta = {**json.loads(str(a["metadata"])), **changes}
    return {**a, "metadata": np.asarray(json.dumps(meta))}


def silent_cases(shared) -> list[Case]:
    """Inputs that once ran silently (exit 0) or failed with a message that named no field:
    an implausible field of view, an unknown control model, no usable hit, a string where a
    number belongs, a wall, pose or control far outside the rest of the data."""
    ok = [_flaser([1.0 + 0.1 * i] * 8, (0.1 * i, 0.0, 0.0), t=float(i)) for i in range(6)]
    cases = []
    for value in ("1e-300", "0", "-90", "nan", "inf", "abc", "720"):
        text = f"PARAM laser_front_laser_fov {value}\n" + "\n".join(ok) + "\n"
        cases.append(
            Case(
                f"log field of view {value}",
                ["slam", "l.clf", "--out", "o"],
                "laser_front_laser_fov",
                _text("l.clf", text),
            )
        )
    text = "PARAM robot_front_laser_max -8\n" + "\n".join(ok) + "\n"
    cases.append(
        Case(
            "log maximum range -8",
            ["slam", "l.clf", "--out", "o"],
            "robot_front_laser_max",
            _text("l.clf", text),
        )
    )
    changes = {
        "control model teleport": lambda a: _metadata(a, control_model="teleport"),
        "control model a number": lambda a: _metadata(a, control_model=3),
        "control model needs three components": lambda a: _metadata(
            a, control_model="odometry_delta"
        ),
        "format version a string": lambda a: {**a, "format_version": np.asarray("one")},
        "max range a string": lambda a: {**a, "max_range": np.asarray("abc")},
        "wall far away": _walls_away,
        "pose far away": _pose_away,
        "control at the loader's limit": _control_away,
        "path too wide for the map": _path_too_wide,
    }
    fields = {
        "control model": "control_model",
        "needs three": "controls",
        "format": "format_version",
        "max range": "max_range",
        "wall": "'walls'",
        "pose": "'poses'",
        "control at": "'controls'",
        "path": "'controls'",
    }
    for name, change in changes.items():
        expect = next(v for k, v in fields.items() if k in name)
        f = name.replace(" ", "_").replace("'", "") + ".npz"
        cases.append(
            Case(f"data {name}", ["slam", f, "--out", "o"], expect, _npz(shared, f, change))
        )
    flat = np.full((12, 7), 2.0)  # every valid reading equal: the range clip, no hit below it
    cases.append(
        Case(
            "bag every valid range at the clip",
            ["slam", "bag", "--out", "o", "--no-odometry"],
            ("'observations'", "no usable hit"),
            lambda d: _ros2_bag(d / "bag", flat),
        )
    )
    cases.append(
        Case(
            "bag two scan topics",
            ["slam", "bag", "--out", "o"],
            "--scan-topic",
            lambda d: _ros2_bag(d / "bag", flat + np.arange(7), ("/a", "/b")),
        )
    )
    cases.append(
        Case(
            "bag stamp backwards",
            ["slam", "bag", "--out", "o"],
            "--lenient",
            lambda d: _ros2_bag(d / "bag", flat + np.arange(7), back=3),
        )
    )
    cases.append(
        Case(
            "npz scan topic",
            ["slam", str(shared["good"]), "--out", "o", "--scan-topic", "/scan"],
            "--scan-topic",
        )
    )
    return cases


def overwrite_cases(shared) -> list[Case]:
    """``--overwrite`` onto a finished run with a bad configuration, input or network file:
    refused before the previous run is touched (the corpus checks every file is unchanged)."""
    good = str(shared["good"])
    over = ["--out", "run", "--overwrite"]
    paper = ["slam", good, *over, "--preset", "paper", "--config", TINY_JSON]
    return [
        Case(
            "overwrite with an unknown config field",
            ["slam", good, *over, "--config", '{"filter_partcles": 64}'],
            "filter_partcles",
            _copy_run(shared),
        ),
        Case(
            "overwrite with a corrupt input",
            ["slam", "d.npz", *over],
            "d.npz",
            lambda d: (_copy_run(shared)(d), _bytes("d.npz", b"not a zip")(d)),
        ),
        Case(
            "overwrite with a missing input",
            ["slam", "missing.npz", *over],
            "missing.npz",
            _copy_run(shared),
        ),
        Case(
            "overwrite with a wall far away",
            ["slam", "w.npz", *over],
            "'walls'",
            lambda d: (_copy_run(shared)(d), _npz(shared, "w.npz", _walls_away)(d)),
        ),
        Case(
            "overwrite with a bad emission file",
            [*paper, "--emission", "n.pt"],
            "n.pt",
            lambda d: (_copy_run(shared)(d), _bytes("n.pt", b"garbage")(d)),
        ),
        Case(
            "overwrite with a bad transition file",
            [*paper, "--transition", "n.pt"],
            "n.pt",
            lambda d: (_copy_run(shared)(d), _bytes("n.pt", _torch_bytes({"a": 1}))(d)),
        ),
        Case(
            "navigate overwrite from a missing run",
            ["navigate", "--from", "missing", "--out", "n.png", "--overwrite"],
            "missing",
            _text("n.png", "keep"),
        ),
        Case(
            "navigate onto an existing plot",
            ["navigate", "--out", "n.png"],
            "--overwrite",
            _text("n.png", "keep"),
        ),
        Case(
            "pretrain into the package",
            ["pretrain", "--out", str(PRETRAINED_DIR / "sub"), "--steps", "10"],
            "--into-package",
        ),
        Case(
            "pretrain onto networks",
            ["pretrain", "--out", "p", "--steps", "10"],
            "--overwrite",
            lambda d: ((d / "p").mkdir(), _text("p/emission_lidar20.pt", "keep")(d)),
        ),
    ]


def corpus(shared) -> list[Case]:
    return (
        option_cases()
        + config_cases(shared)
        + data_cases(shared)
        + log_cases(shared)
        + resume_cases(shared)
        + network_cases(shared)
        + output_cases(shared)
        + silent_cases(shared)
        + overwrite_cases(shared)
    )


# ------------------------------------------------------------------------------ running
def _snapshot(d: Path) -> dict[str, str]:
    return {
        str(p.relative_to(d)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(d.rglob("*"))
        if p.is_file()
    }


def run_case(case: Case, folder: Path) -> dict:
    """Run one case in ``folder``; returns what happened (see the module doc)."""
    from pyro_slam import cli

    folder.mkdir(parents=True, exist_ok=True)
    if case.setup is not None:
        case.setup(folder)
    before = _snapshot(folder)
    err, out = io.StringIO(), io.StringIO()
    cwd = os.getcwd()
    os.chdir(folder)
    traceback = None
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
            try:
                rc = cli.main(case.argv)
            except SystemExit as e:
                rc = e.code if isinstance(e.code, int) else 2
    except Exception as e:  # an exception that escaped the command: a traceback for a user
        rc, traceback = None, f"{type(e).__name__}: {e}"
    finally:
        os.chdir(cwd)
    after = _snapshot(folder)
    message = err.getvalue().strip()
    expect = (case.expect,) if isinstance(case.expect, str) else case.expect
    return {
        "name": case.name,
        "rc": rc,
        "traceback": traceback or ("Traceback" in message and message),
        "message": message,
        "one_line": message.count("\n") == 0 and message.startswith("pyro-slam"),
        "names_it": any(e in message for e in expect),
        "lost": sorted(k for k, v in before.items() if after.get(k) != v),
        "executed": (folder / MARKER).exists(),
    }


def main() -> int:
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        shared = make_shared(root / "shared")
        results = [run_case(c, root / f"case{i}") for i, c in enumerate(corpus(shared))]
    bad = [
        r
        for r in results
        if r["rc"] != 2
        or r["traceback"]
        or not r["one_line"]
        or not r["names_it"]
        or r["lost"]
        or r["executed"]
    ]
    counts = {
        "cases": len(results),
        "tracebacks": sum(bool(r["traceback"]) for r in results),
        "exit_0": sum(r["rc"] == 0 for r in results),
        "not_exit_2": sum(r["rc"] != 2 for r in results),
        "not_one_line": sum(not r["one_line"] for r in results),
        "not_naming_the_problem": sum(not r["names_it"] for r in results),
        "files_lost": sum(len(r["lost"]) for r in results),
        "executed": sum(r["executed"] for r in results),
        "failures": [{k: r[k] for k in ("name", "rc", "message", "traceback")} for r in bad],
    }
    print(json.dumps(counts, indent=2))
    return 0 if not bad else 1


if __name__ == "__main__":
    # run as a script, this folder comes first on sys.path and its tests/simulators folder
    # would hide the simulators package: look from the repository root instead
    sys.path[0] = str(Path(__file__).resolve().parents[1])
    sys.exit(main())
