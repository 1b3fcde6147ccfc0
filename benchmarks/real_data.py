"""DVBF-LM SLAM on real laser logs vs odometry alone vs MRPT's icp-slam.

    python -m benchmarks.real_data --out out/real_data            # both logs, 10 seeds, 1 thread
    python -m benchmarks.real_data --steps 300 --seeds 1 --out /tmp/rd   # quick look
    python -m benchmarks.real_data --config '{"filter": {"particles": 256}}' --out out/rd_k256

Logs (``--data``, default ``../shared/data``; sources and checksums in docs/real_data.md):

* ``mit-csail.clf``: raw odometry from the FLASER odometry fields, 361 beams. No ground truth:
  the metric is *scan consistency* (:func:`pyro_slam.metrics.log_scan_consistency`, the figure
  ``pyro-slam slam`` writes into ``metrics.json`` too): every scan (every 2nd beam, readings
  below the 99th range percentile), reprojected with a system's poses, is matched
  point-to-nearest-point (scipy cKDTree) against the scans >= 10 steps away; mean distance
  (capped at 1 m), lower is better.
* ``intel.gfs.log``: GMapping-corrected scans (180 beams). Its FLASER poses are the reference;
  it has **no raw odometry**, so every system starts from odometry *made* from the GMapping
  poses plus Gaussian noise (per step: translation std 5 % of the step + 1 cm, heading std
  3 % of the turn + 0.01 rad, seed 0). Metrics: the Kümmerle et al. (2009) relation error
  (all consecutive pairs + 1000 random pairs <= 50 scans apart, from the GMapping poses) and the
  ATE after a rigid SE(2) alignment, plus scan consistency.

Scan consistency alone rewards a trajectory that collapses (all scans piled in one place agree
with each other), so each row also reports the path length, which odometry measures well.

Systems: odometry (dead reckoning), DVBF-LM online SLAM (``pyro-slam slam`` defaults for real
logs: the ``real`` preset adapted to each log, :mod:`pyro_slam.slam.presets`; ``--preset`` and
``--config`` overrides) and, on Intel, offline SLAM with the same configuration
(``--no-offline`` skips it), MRPT ``icp-slam`` (Debian ``mrpt-apps`` +
``mrpt-common`` for the shipped ini): ``carmen2rawlog`` then ``icp-slam`` with
``icp-slam_demo_classic.ini``, GUI / 3D-scene output off. MRPT 2.5.8's ``carmen2rawlog`` stamps
every observation with one and the same time, so icp-slam cannot use the odometry (its pose
extrapolator rejects zero time steps) and, with the ini's 0.2 m / 5 deg "localise only after
this much odometric motion" gates, never runs ICP after the first scan; the script therefore
sets ``localizationLinDistance = localizationAngDistance = 0`` (ICP against the map at every
scan, i.e. pure scan matching without an odometry prior). Without MRPT installed the MRPT rows
are skipped with a message.

Seeds: DVBF-LM runs with seeds 0..N-1 (``--seeds N``, default 10; the Intel odometry noise keeps
seed 0, odometry and MRPT have no seed). Each DVBF-LM row holds every figure as the mean over the
seeds, ``std`` their sample standard deviations and ``worst`` the seed with the highest CSAIL
scan consistency / Intel relation error; stderr shows mean ± std and the worst run per row. Each
(log, mode, seed) run is kept in ``OUT/runs/`` and read back when the script is run again into
the same ``--out`` (with the same configuration, ``--steps`` and ``--threads``; otherwise it
stops), so a long run can be continued, or given more seeds.

Wall time per scan: whole-run wall clock / scans, ``--threads`` torch threads (default 1) for
DVBF-LM; icp-slam's process wall clock for MRPT.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from benchmarks._common import add_config_args, add_threads_arg, check_out_config, slam_config
from pyro_slam import metrics
from pyro_slam.data import atomic_write
from pyro_slam.io import (
    odometry_poses,
    read_any,
    relation_error,
    relations_from_reference,
    write_carmen,
)
from pyro_slam.io.common import relative
from pyro_slam.slam import presets
from pyro_slam.slam.outputs import run_slam

REPO = Path(__file__).resolve().parents[1]

DATA = REPO.parent / "shared" / "data"
MRPT_INI = Path("/usr/share/mrpt/config_files/icp-slam/icp-slam_demo_classic.ini")


# ----------------------------------------------------------------------------------- data
def noisy_odometry(tr, seed=0, trans_frac=0.05, trans_floor=0.01, rot_frac=0.03, rot_floor=0.01):
    """Odometry made from the reference poses plus noise (logs without raw odometry)."""
    rng = np.random.default_rng(seed)
    ref = np.asarray(tr.poses, dtype=np.float64)
    u = relative(ref[:-1], ref[1:])  # [T-1, 3] exact increments
    step = np.linalg.norm(u[:, :2], axis=1, keepdims=True)
    u[:, :2] += rng.normal(size=(len(u), 2)) * (trans_frac * step + trans_floor)
    u[:, 2] += rng.normal(size=len(u)) * (rot_frac * np.abs(u[:, 2]) + rot_floor)
    meta = {**tr.metadata, "odometry_origin": [float(v) for v in ref[0]]}
    meta["odometry_source"] = f"GMapping poses + noise (seed {seed})"
    return replace(tr, controls=u, metadata=meta)


# ----------------------------------------------------------------------------------- systems
def log_config(tr, preset: str = "real", overrides: dict | None = None):
    """The SLAM configuration for log ``tr``: ``preset`` adapted to the log (the ``real``
    preset's beam stride, range clip and odometry noise), then the ``--config`` overrides
    (:func:`pyro_slam.slam.presets.configure`, as the command line chooses it)."""
    return presets.configure(preset, tr, overrides)[1]


def run_dvbf(tr, out: Path, cfg, preset: str, seed: int = 0, mode: str = "online", threads=None):
    """DVBF-LM on ``tr`` into the folder ``out``: ``([T, 3] pose means, [T, 3] pose stds, wall
    seconds)``."""
    rep = run_slam(tr, out, mode, cfg, progress=False, seed=seed, preset=preset, threads=threads)
    with np.load(out / "posterior.npz") as post:
        return post["pose_mean"], post["pose_std"], rep["wall_time_s"]


def mrpt_available() -> str | None:
    """None when carmen2rawlog, icp-slam and the shipped ini are there, else why not."""
    missing = [b for b in ("carmen2rawlog", "icp-slam") if shutil.which(b) is None]
    if missing:
        return f"{', '.join(missing)} not found (apt-get install mrpt-apps)"
    if not MRPT_INI.is_file():
        return f"{MRPT_INI} not found (apt-get install mrpt-common)"
    return None


def run_mrpt(tr, work: Path):
    """icp-slam on ``tr`` (written as a CARMEN log): ``([T, 3] poses, wall seconds)``."""
    work.mkdir(parents=True, exist_ok=True)
    clf, rawlog = work / "log.clf", work / "log.rawlog"
    # FLASER pose fields = odometry too: carmen2rawlog turns them into odometry observations,
    # and MRPT must not see the reference (Intel's GMapping) poses
    write_carmen(replace(tr, poses=None), clf)
    subprocess.run(
        ["carmen2rawlog", "-q", "-w", "-i", clf.name, "-o", rawlog.name],  # (in cwd)
        check=True,
        capture_output=True,
        cwd=work,
    )
    ini = MRPT_INI.read_text()
    subs = {
        "SHOW_PROGRESS_3D_REAL_TIME": "0",
        "SAVE_3D_SCENE": "0",
        "logOutput_dir": "icp_out",
        "LOG_FREQUENCY": "100000",
        "localizationLinDistance": "0.0",
        "localizationAngDistance": "0.0",
    }
    for key, value in subs.items():
        ini = re.sub(rf"(?m)^{key}\s*=.*$", f"{key} = {value}", ini)
    (work / "icp.ini").write_text(ini)
    t0 = time.perf_counter()
    res = subprocess.run(
        ["icp-slam", "icp.ini", rawlog.name],
        cwd=work,
        capture_output=True,
        text=True,
        stdin=subprocess.DEVNULL,
        timeout=1800,
    )
    wall = time.perf_counter() - t0
    (work / "icp.log").write_text(res.stdout + res.stderr)
    path = np.loadtxt(work / "icp_out" / "log_estimated_path.txt")  # [N_obs, 4]: i x y phi
    listing = subprocess.run(
        ["rawlog-edit", "--list-timestamps", "-i", rawlog.name, "--text-file-output", "ts.txt"],
        cwd=work,
        capture_output=True,
        text=True,
    )
    labels = [ln.split()[1] for ln in (work / "ts.txt").read_text().splitlines() if ln.strip()]
    if listing.returncode or len(labels) != len(path):
        raise RuntimeError(f"icp-slam output: {len(path)} poses for {len(labels)} observations")
    scans = np.array([lab == "FLASER" for lab in labels])
    poses = path[scans][:, 1:4]
    if len(poses) != tr.num_steps:
        raise RuntimeError(f"icp-slam gave {len(poses)} scan poses for {tr.num_steps} scans")
    return poses, wall


# ----------------------------------------------------------------------------------- metrics
def evaluate(tr, tr_eval, poses, ref=None, relations=None, std=None):
    """A system's row on the log ``tr`` (``tr_eval``: its :func:`metrics.consistency_scans`):
    the quoted scan consistency, the path length and, with a reference, the relation error and
    the aligned ATE, and, for a posterior (its pose stds ``std [T, 3]``), its calibration
    against the reference (:func:`metrics.calibration`)."""
    # a trajectory that collapses onto itself scores well on scan consistency (its scans pile
    # up on each other); the path length (odometry measures it well) exposes that
    out = {
        "scan_consistency": metrics.log_scan_consistency(tr, poses, tr_eval),
        "path_length_m": float(metrics.distance_travelled(poses)[-1]),
    }
    if ref is not None:
        out["relation_error"] = relation_error(tr_eval.timestamps, poses, relations)
        out["ate_aligned"] = metrics.ate(poses, ref, align=True)
        if std is not None:
            out["calibration"] = metrics.calibration(std, poses, ref, metrics.CALIBRATION_START)
    return out


def map_figure(tr_eval, systems: dict, path: Path, title: str):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(systems), figsize=(4.2 * len(systems), 4.2), squeeze=False)
    for ax, (name, poses) in zip(axes[0], systems.items()):
        xy, _ = metrics.scan_points(tr_eval, poses)
        ax.scatter(xy[:, 0], xy[:, 1], s=0.15, c="k", alpha=0.3, linewidths=0)
        ax.plot(poses[:, 0], poses[:, 1], color="tab:blue", lw=0.6)
        ax.set_aspect("equal")
        ax.set_title(name, fontsize=9)
        ax.tick_params(labelsize=6)
    fig.suptitle(title, fontsize=10)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=70, bbox_inches="tight")
    plt.close(fig)


# ----------------------------------------------------------------------------------- seeds
SEEDED = ("DVBF-LM", "DVBF-LM offline")  # the rows run once per seed (the others have none)
WORST_BY = {  # a log's figure that names its worst seed (higher is worse)
    "mit-csail": ("scan_consistency", "mean"),
    "intel": ("relation_error", "trans_mean"),
}


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _over_seeds(values: list, stat):
    """``stat`` of one figure over the seeds' runs: dicts figure by figure; numbers (null where
    any run has none); other values kept where all runs agree, else null."""
    if all(isinstance(v, dict) for v in values):
        keys = list(dict.fromkeys(k for v in values for k in v))
        return {k: _over_seeds([v.get(k) for v in values], stat) for k in keys}
    if all(_number(v) for v in values):
        return stat(values)
    return values[0] if all(v == values[0] for v in values) else None


def _mean(values: list):
    """The mean; a figure that every run shares (a count, a setting) as it is."""
    return values[0] if len(set(values)) == 1 else float(np.mean(values))


def _std(values: list) -> float:
    """The sample standard deviation (0 for one run)."""
    return float(np.std(values, ddof=1)) if len(values) > 1 else 0.0


def over_seeds(runs: dict[int, dict], worst_by: tuple[str, ...]) -> dict:
    """One system's row from its runs ``{seed: row}`` on one log: every figure the mean over the
    seeds (the rows' own keys, so a one-seed row reads as before), ``std`` the same figures'
    sample standard deviations, ``worst`` the run with the highest ``worst_by`` figure (its
    ``seed``, the figure's name ``by`` and ``value``, and that figure for every seed,
    ``per_seed``), ``seeds`` the seeds."""
    seeds = sorted(runs)
    rows = [runs[s] for s in seeds]
    row = _over_seeds(rows, _mean)
    row["std"] = _over_seeds(rows, _std)

    def figure(r):
        for k in worst_by:
            r = r.get(k) if isinstance(r, dict) else None
        return r if _number(r) else None

    per_seed = {str(s): figure(runs[s]) for s in seeds}
    scored = [s for s in seeds if per_seed[str(s)] is not None]
    worst = max(scored, key=lambda s: per_seed[str(s)]) if scored else None
    row["worst"] = {
        "seed": worst,
        "by": ".".join(worst_by),
        "value": None if worst is None else per_seed[str(worst)],
        "per_seed": per_seed,
    }
    row["seeds"] = seeds
    return row


def seeded_rows(name, tr, tr_eval, out: Path, cfg, preset, modes, seeds, ref, rel, threads):
    """The DVBF-LM rows of one log over ``seeds``, :func:`over_seeds`; each (log, mode, seed)
    run is kept in ``out/runs/`` and read back instead of rerun when the benchmark is run again
    into the same ``--out``. Returns ``(rows, seed 0's online poses or None)``."""
    rows, first = {}, None
    for mode in modes:
        label = "DVBF-LM" if mode == "online" else "DVBF-LM offline"
        runs = {}
        for seed in seeds:
            folder = out / f"{name}_dvbf{'' if mode == 'online' else '_offline'}_seed{seed}"
            kept = out / "runs" / f"{name}_{mode}_seed{seed}.json"
            if kept.is_file():
                runs[seed] = json.loads(kept.read_text())
            else:
                poses, std, wall = run_dvbf(tr, folder, cfg, preset, seed, mode, threads)
                row = {**evaluate(tr, tr_eval, poses, ref, rel, std)}
                row["seconds_per_scan"] = wall / tr.num_steps
                text = json.dumps(row, indent=1, default=float)
                kept.parent.mkdir(parents=True, exist_ok=True)
                atomic_write(kept, lambda f, text=text: f.write(text.encode()))
                runs[seed] = json.loads(text)  # as a resumed run reads it
            if mode == "online" and seed == seeds[0]:
                with np.load(folder / "posterior.npz") as post:
                    first = post["pose_mean"]
        rows[label] = over_seeds(runs, WORST_BY[name])
    return rows, first


def benchmark_log(
    name,
    tr,
    out: Path,
    img: Path,
    use_mrpt: bool,
    reference: bool,
    preset="real",
    overrides=None,
    offline: bool = False,
    seeds=(0,),
    threads=None,
):
    print(f"== {name}: {tr.num_steps} scans, {tr.num_beams} beams", file=sys.stderr)
    cfg = log_config(tr, preset, overrides)
    # the metric reads the log on its own scans (every 2nd beam), whatever SLAM runs
    tr_eval = metrics.consistency_scans(tr)
    ref = tr.poses if reference else None
    rel = None
    if reference:
        rel = relations_from_reference(tr.timestamps, ref, n_random=1000, max_steps=50)
    origin = ref[0] if reference else np.zeros(3)
    rows, trajs = {}, {}

    t0 = time.perf_counter()
    odo = odometry_poses(tr, origin)
    odo_wall = time.perf_counter() - t0
    trajs["odometry"] = odo
    rows["odometry"] = evaluate(tr, tr_eval, odo, ref, rel)
    rows["odometry"]["seconds_per_scan"] = odo_wall / tr.num_steps

    # the offline mode on the log with reference poses (rounds over the whole traversal)
    modes = ("online", "offline") if offline else ("online",)
    dvbf, trajs[f"DVBF-LM (seed {seeds[0]})"] = seeded_rows(
        name, tr, tr_eval, out, cfg, preset, modes, list(seeds), ref, rel, threads
    )
    rows.update(dvbf)

    if use_mrpt:
        try:
            mp, wall = run_mrpt(tr, out / f"{name}_mrpt")
            trajs["MRPT icp-slam"] = mp
            rows["MRPT icp-slam"] = evaluate(tr, tr_eval, mp, ref, rel)
            rows["MRPT icp-slam"]["seconds_per_scan"] = wall / tr.num_steps
        except (subprocess.SubprocessError, OSError, RuntimeError, ValueError) as e:
            rows["MRPT icp-slam"] = {"skipped": f"icp-slam failed: {e}"}
            print(f"MRPT on {name} failed: {e}", file=sys.stderr)
    if reference:
        trajs = {"GMapping (reference)": ref, **trajs}
        rows["GMapping (reference)"] = evaluate(tr, tr_eval, ref, ref, rel)
    map_figure(tr_eval, trajs, img / f"real_{name}.png", f"{name}: scans reprojected")
    return rows


def headline(result: dict) -> dict:
    """The figures the results page quotes, first in the JSON object, DVBF-LM's each a mean over
    the seeds: Intel's relation error (mean translation, m) for DVBF-LM and odometry, CSAIL's
    mean scan consistency for DVBF-LM (and its worst seed's) and MRPT (null without MRPT), each
    log's path ratio (DVBF-LM path length / odometry's) and DVBF-LM's wall-clock ms per scan
    over both logs (online), Intel's offline path ratio and relation error (null with
    ``--no-offline``), and the number of seeds."""
    csail, intel = result["mit-csail"], result["intel"]

    def ratio(rows, system="DVBF-LM"):  # null where odometry did not move (--steps)
        if system not in rows:
            return None
        odo = rows["odometry"]["path_length_m"]
        return rows[system]["path_length_m"] / odo if odo > 0 else None

    mrpt = csail.get("MRPT icp-slam", {}).get("scan_consistency", {}).get("mean")
    scans = result["scans"]
    wall = sum(
        rows["DVBF-LM"]["seconds_per_scan"] * scans[log]
        for log, rows in (("mit-csail", csail), ("intel", intel))
    )
    return {
        "intel_relation_error_trans_m": intel["DVBF-LM"]["relation_error"]["trans_mean"],
        "intel_odometry_relation_error_trans_m": intel["odometry"]["relation_error"]["trans_mean"],
        "csail_scan_consistency_mean_m": csail["DVBF-LM"]["scan_consistency"]["mean"],
        "csail_scan_consistency_worst_m": csail["DVBF-LM"]["worst"]["value"],
        "csail_odometry_scan_consistency_mean_m": csail["odometry"]["scan_consistency"]["mean"],
        "csail_mrpt_scan_consistency_mean_m": mrpt,
        "csail_path_ratio": ratio(csail),
        "intel_path_ratio": ratio(intel),
        "intel_offline_path_ratio": ratio(intel, "DVBF-LM offline"),
        "intel_offline_relation_error_trans_m": intel.get("DVBF-LM offline", {})
        .get("relation_error", {})
        .get("trans_mean"),
        "ms_per_scan": 1000 * wall / sum(scans.values()),
        "seeds": len(csail["DVBF-LM"]["seeds"]),
    }


def seed_table(result: dict) -> list[str]:
    """One line per log and seeded row: its figures as mean ± std over the seeds, and the worst
    run."""
    figures = (
        ("scan consistency", ("scan_consistency", "mean"), "m"),
        ("path", ("path_length_m",), "m"),
        ("relation error", ("relation_error", "trans_mean"), "m"),
        ("std/error", ("calibration", "std_over_error"), ""),
        ("aligned", ("calibration", "std_over_aligned_error"), ""),
        ("2-sigma coverage", ("calibration", "coverage_2sigma"), ""),
        ("s/scan", ("seconds_per_scan",), ""),
    )
    lines = []
    for log in ("mit-csail", "intel"):
        for system in SEEDED:
            row = result[log].get(system)
            if row is None:
                continue
            parts = []
            for label, keys, unit in figures:
                mean, std = row, row["std"]
                for k in keys:
                    mean, std = (mean or {}).get(k), (std or {}).get(k)
                if _number(mean):
                    parts.append(f"{label} {mean:.4g} ± {std:.2g}{unit and ' ' + unit}")
            w = row["worst"]
            worst = (
                ""
                if w["seed"] is None
                else f"; worst {w['by']} {w['value']:.4g} (seed {w['seed']})"
            )
            lines.append(f"{log} {system}, {len(row['seeds'])} seeds: {', '.join(parts)}{worst}")
    return lines


def parse(argv):
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.real_data", description=__doc__.split("\n")[0]
    )
    p.add_argument("--out", type=Path, default=Path("out/real_data"))
    p.add_argument("--img", type=Path, default=REPO / "docs" / "img")
    p.add_argument("--steps", type=int, default=0, help="first N scans of each log only")
    p.add_argument("--data", type=Path, default=DATA)
    p.add_argument("--no-mrpt", action="store_true")
    p.add_argument(
        "--no-offline", action="store_true", help="skip offline SLAM on Intel (the reference log)"
    )
    p.add_argument(
        "--seeds",
        type=int,
        default=10,
        metavar="N",
        help="run DVBF-LM with seeds 0..N-1 (default 10); rows report mean, std and the worst seed",
    )
    add_config_args(p, "real")
    add_threads_arg(p)
    args = p.parse_args(argv)
    if args.seeds < 1:
        p.error(f"--seeds: must be >= 1, got {args.seeds}")
    slam_config(p, args.preset, args.config)  # a bad --preset / --config: a usage error now
    return args


def main(argv=None):
    args = parse(argv)
    overrides = json.loads(args.config)
    torch.set_num_threads(args.threads)
    why = "--no-mrpt" if args.no_mrpt else mrpt_available()
    if why:
        print(f"MRPT icp-slam skipped: {why}", file=sys.stderr)

    def cut(tr):
        return tr.slice(0, min(args.steps, tr.num_steps)) if args.steps else tr

    csail = cut(read_any(args.data / "mit-csail.clf"))
    intel = cut(noisy_odometry(read_any(args.data / "intel.gfs.log")))
    kw = {"preset": args.preset, "overrides": overrides}
    configs = {
        "mit-csail": log_config(csail, **kw).to_dict(),
        "intel": log_config(intel, **kw).to_dict(),
    }
    # the kept runs of out/runs/ belong to this configuration, length and thread count
    record = {"preset": args.preset, "config": configs, "steps": args.steps}
    check_out_config(args.out / "runs" / "config.json", {**record, "threads": args.threads})
    kw.update(seeds=range(args.seeds), threads=args.threads)
    result = {
        "preset": args.preset,
        "config": configs,
        "mit-csail": benchmark_log("mit-csail", csail, args.out, args.img, not why, False, **kw),
        "intel": benchmark_log(
            "intel", intel, args.out, args.img, not why, True, **kw, offline=not args.no_offline
        ),
        "mrpt": why or "icp-slam (MRPT) with icp-slam_demo_classic.ini, localization gates 0",
        "intel_odometry": "GMapping poses + Gaussian noise (no raw odometry in intel.gfs.log)",
        "steps": args.steps or "all",
        "threads": args.threads,
        "scans": {"mit-csail": csail.num_steps, "intel": intel.num_steps},
    }
    # the log's own ODOM stream, for reference (drifts far: not used as raw odometry)
    raw = cut(read_any(args.data / "intel.gfs.log"))
    result["intel_log_odom_relation_error"] = relation_error(
        raw.timestamps,
        odometry_poses(raw, raw.poses[0]),
        relations_from_reference(raw.timestamps, raw.poses, n_random=1000, max_steps=50),
    )
    print("\n".join(seed_table(result)), file=sys.stderr)
    text = json.dumps({**headline(result), **result}, indent=2, default=float)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "real_data.json").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
