"""Probe visual SLAM's online sweep on one test maze: why revisits do not pull it back.

Runs the online sweep that ``benchmarks/visual_slam.py`` starts offline SLAM from (its
configuration, its pretrained emission, the same traversal) and, every ``--every`` steps,
scores the newest image against the current map mean on a grid of headings (true heading
``+-0.5`` rad) at the true position and at the estimated one (``log p(x_t | M, z)`` with the
filter's ``sigma_E``). It also records the particle cloud's std and its trust in the map,
and (``revisit_stats``) whether the estimate's heading follows odometry and how well the
places it revisits late were mapped on the first visit. The
diagnosis in docs/visual_slam.md ("Session 16") reads it:

* **cloud std vs error**: a cloud far narrower than its own error cannot move to the truth
  however the map scores it;
* **true pose vs estimate**: whether the map, at this moment, prefers the truth (an inference
  failure) or the estimate (the map has been rewritten to agree with the drifted estimate);
* **best heading at the true position**: how far the map's panorama there is rotated.

    python benchmarks/visual_slam_probe.py --maze 1005 --out out/visual_probe     # ~10 min

Writes ``OUT/probe_m<maze>.json`` (the probes and per-step trust) and prints a summary.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def revisit_stats(est, truth, pi, window=100, turn=0.06, radius=0.02, gap=300, tail=1200):
    """Does the estimate follow odometry, and were the places it revisits late mapped well?

    ``est``, ``truth``, ``pi`` ``[T, 3]``. Returns

    * ``odometry_windows``: the ``window``-step windows in which path integration's (signed,
      unwrapped) heading error changed by more than ``turn`` rad, and
      ``odometry_windows_max_gap``, the largest difference between the estimate's change and
      path integration's over them (0: the estimate's heading follows odometry there);
    * over the last ``tail`` steps, every ``window`` steps that revisit a place (true position
      within ``radius`` of one at least ``gap`` steps earlier): the first-visit steps' range and
      the estimate's position / absolute heading error there (``first_visit_*``), and the
      estimate's absolute heading error at the revisits (``revisit_heading_error``).
    """
    T = len(truth)
    h_est = np.unwrap(est[:, 2] - truth[:, 2])  # [T]
    h_pi = np.unwrap(pi[:, 2] - truth[:, 2])
    gaps = [
        abs((h_est[t + window] - h_est[t]) - (h_pi[t + window] - h_pi[t]))
        for t in range(0, T - window, window)
        if abs(h_pi[t + window] - h_pi[t]) > turn
    ]
    err = np.linalg.norm(est[:, :2] - truth[:, :2], axis=1)  # [T]
    habs = np.abs(np.angle(np.exp(1j * (est[:, 2] - truth[:, 2]))))  # [T]
    first, later = [], []
    for t in range(max(T - tail, gap), T, window):
        d = np.linalg.norm(truth[: t - gap + 1, :2] - truth[t, :2], axis=1)
        hits = np.flatnonzero(d < radius)
        if len(hits):
            first.append(int(hits[0]))
            later.append(t)
    out = {"odometry_windows": len(gaps), "odometry_windows_max_gap": float(max(gaps, default=0))}
    if first:
        out.update(
            revisits=len(first),
            first_visit_steps=[min(first), max(first)],
            first_visit_error_max=float(err[first].max()),
            first_visit_heading_error_max=float(habs[first].max()),
            revisit_heading_error=[float(habs[later].min()), float(habs[later].max())],
        )
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--maze", type=int, default=1005, help="a test-maze seed of visual_slam.py")
    p.add_argument("--steps", type=int, default=5000)
    p.add_argument("--every", type=int, default=250, help="probe every N steps")
    p.add_argument("--pretrain-steps", type=int, default=1500, help="emission SGD steps")
    p.add_argument("--pretrain-traversal", type=int, default=3000, help="steps on maze 100")
    p.add_argument("--config", default="{}", help="JSON SLAMConfig overrides")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", type=Path, default=Path("out/visual_probe"))
    args = p.parse_args(argv)
    import visual_slam as vs

    if args.maze not in vs.MAZE_SEEDS:
        p.error(f"--maze {args.maze}: not a test maze (these are {list(vs.MAZE_SEEDS)})")
    if not 0 < args.every < args.steps:
        p.error(f"--every must be in (0, {args.steps}), got {args.every}")
    import torch

    torch.set_num_threads(args.threads)
    from pyro_slam.metrics import heading_error, localisation_error
    from pyro_slam.slam import SLAM, SLAMConfig, path_integration

    args.out.mkdir(parents=True, exist_ok=True)
    cfg = SLAMConfig(**{**vs.BENCH_CONFIG, **json.loads(args.config)})
    em, _ = vs.pretrained_emission(
        args.out / "emission_image.pt", cfg, args.pretrain_traversal, args.pretrain_steps
    )
    tr = vs._traversal(args.maze, 1, args.steps)
    slam = SLAM(tr, cfg, emission=em)
    truth = torch.as_tensor(tr.poses, dtype=torch.float32)  # [T, 3]
    dh = torch.arange(-20, 21) * 0.025  # [H] heading offsets from the true heading
    trust, probes = [], []
    filter_step = slam._filter_step

    def probed_step(t: int, M):
        filter_step(t, M)
        trust.append(float(slam.pf.cloud_trust(slam.particles, M)))
        if t == 0 or t % args.every:
            return
        est = slam.particles.mean()  # [3]

        @torch.no_grad()
        def loglik(z):  # [P, 3] -> log p(x_t | map mean, z) [P]
            mean = slam.model.emission_mean(M.loc, z)  # [P, N]
            return slam.model.emission_log_prob(slam.obs[t], mean, None, cfg.filter_sigma)

        row = {"t": t, "estimate": est.tolist(), "truth": truth[t].tolist()}
        for name, base in (("true_position", truth[t]), ("estimated_position", est)):
            z = base.repeat(len(dh), 1)  # [H, 3]
            z[:, 2] = truth[t, 2] + dh
            row[f"loglik_{name}"] = loglik(z).tolist()  # [H]
        ll = loglik(torch.stack([truth[t], est]))  # [2]
        row["loglik_truth_minus_estimate"] = float(ll[0] - ll[1])
        row["cloud_std"] = slam.particles.z.std(0).tolist()  # [3]
        probes.append(row)

    slam._filter_step = probed_step
    res = slam.run("online", progress=True)
    pi = path_integration(tr, slam.model.transition)  # [T, 3]
    err = localisation_error(res["mean"], tr.poses)  # [T]
    herr = heading_error(res["mean"][:, 2], tr.poses[:, 2])  # [T]
    for row in probes:
        t = row["t"]
        row["error"], row["heading_error"] = float(err[t]), float(herr[t])
        row["best_heading_offset_at_truth"] = float(dh[int(np.argmax(row["loglik_true_position"]))])
    late = [r for r in probes if r["t"] >= args.steps // 2]
    summary = {
        "maze": args.maze,
        "steps": args.steps,
        "final_error": float(err[-1]),
        "heading_offsets": dh.tolist(),
        "late_probes": len(late),
        "late_heading_error_median": float(np.median([r["heading_error"] for r in late])),
        "late_cloud_heading_std_median": float(np.median([r["cloud_std"][2] for r in late])),
        "late_truth_preferred": int(sum(r["loglik_truth_minus_estimate"] > 0 for r in late)),
        "late_best_heading_offset_at_truth_abs_median": float(
            np.median([abs(r["best_heading_offset_at_truth"]) for r in late])
        ),
        "trust_mean_per_quarter": [float(q.mean()) for q in np.array_split(np.array(trust), 4)],
        **revisit_stats(res["mean"], tr.poses, pi),
    }
    (args.out / f"probe_m{args.maze}.json").write_text(
        json.dumps({**summary, "probes": probes, "trust": trust})
    )
    for r in probes:
        print(json.dumps({k: round(r[k], 4) for k in ("t", "error", "heading_error",
              "loglik_truth_minus_estimate", "best_heading_offset_at_truth")}
              | {"cloud_heading_std": round(r["cloud_std"][2], 4)}))  # fmt: skip
    print(json.dumps({k: v for k, v in summary.items() if k != "heading_offsets"}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
