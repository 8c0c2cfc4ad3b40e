"""Multi-animal identity: who is who across four cameras, against the true identities and per-track triangulation.

    .venv/bin/python bench/bench_group.py [--seeds 0 1 2] [--frames 3000] [--animals 2 3] [--quick] [--out group]

The data (:mod:`graph.simulate_group`, every option at its default): the synthetic ring of four
cameras (:func:`graph.simulate.ring_rig`, 1920x1080, 4 m radius), groups of 2 and 3 animals of 12
markers crossing and touching, 60 fps, 3000 frames a run, seeds 0, 1, 2; each camera's 2D tracker
swaps two slots' identities in 2 % of its frames (persistently, independently per camera), loses an
instance in 5 % of (camera, frame) pairs and a point in 5 %, 2 px noise, 2 % confident outliers
(sigma 100 px, likelihood as high as a good point's).

What runs on every group, on the same detections:

* ``ours``: :func:`graph.solve.identity.assign` on the tracker's slots, the number of individuals
  found (not given), then each individual solved alone by ``fte`` on free points
  (``SolveOptions(method="fte", fps=60, skeleton="points")``, every other option at its default);
* ``ours-tri``: the same individuals, each by the robust triangulation alone (``method="tri"``):
  identity without the smoother;
* ``oracle``: the same ``fte`` solve per animal on the slots given the true identities
  (``GroupRun.true_tracks``, slot ``k`` is animal ``k`` in every camera and frame); and
  ``oracle-tri``, its triangulation, the reference for ``ours-tri``;
* ``per-track``: what sleap-anipose does with a multi-animal session: each 2D slot name taken as one
  animal in every camera, its points with likelihood below 0.5 set NaN (as
  ``harness.anipose_points`` does; the simulator's good points are 0.8-1, so Anipose's 0.8 gives
  the same), triangulated by aniposelib's ``CameraGroup.triangulate`` (DLT from all views, the
  ``CameraGroup`` from the Anipose TOML we write for the rig).

Every method's 3D individuals are judged by :func:`graph.metrics.group_error`: each individual is
matched to an animal for the whole run (Hungarian method on the median marker distance), and a 3D
identity switch is a frame in which the animal nearest an individual differs from that of its last
frame with an estimate; switches are given per 10,000 animal-frames (individual-frames with an
estimate), and each animal's 3D error (mean, median) against its matched individual, in mm.

Identity is also judged in 2D: the share of detections (a slot with at least 3 points above the
threshold) given to an individual that is not their true animal (the individual's animal by the
run's match above), as the tracker gave them (each slot one individual) and after ``assign``, and the
share ``assign`` left to no one; beside them the tracker's simulated swaps and the 2D switches
``assign`` reports corrected (a slot's individual changing between its frames, per camera).

The targets: per animal, ``ours`` mean error at most 1.2 times the ``oracle``'s (the cost of not
being told who is who; the worst ratio over animals and runs is reported, and the median's beside
it), and at most 1 switch per 10,000 animal-frames, pooled over all runs.

Times are wall seconds (``time.perf_counter``) after one untimed warm-up of every method on a short
group (numba's kernels, jax's compile): ``assign`` alone, and the whole ``ours`` pipeline (assign and
every individual's fte solve), with frames per second of the run (frames / seconds); each method's
seconds in the first table (``ours-tri``'s include ``assign``'s). The machine is
shared (2 cores): its load at the start and end is recorded.

``--quick``: one seed, 600 frames, to check that it runs. Prints Markdown tables and writes
bench/results/group.json (``--out``).
"""

from __future__ import annotations

import argparse
import os
import time
import warnings

import harness as h
import numpy as np

from graph.api import SolveOptions, solve
from graph.metrics import group_error
from graph.simulate import ring_rig
from graph.simulate_group import simulate_group
from graph.solve.identity import assign

FPS = 60.0
THRESHOLD = 0.5  # likelihood below which a point is left out (assign's and the solves' default)
TARGET_RATIO = 1.2
TARGET_SWITCHES = 1.0  # per 10,000 animal-frames, pooled
METHODS = ("ours", "ours-tri", "oracle", "oracle-tri", "per-track")


def fte(fps: float) -> SolveOptions:
    return SolveOptions(method="fte", fps=fps, skeleton="points")


def tri(fps: float) -> SolveOptions:
    return SolveOptions(method="tri", fps=fps, skeleton="points")


def solve_each(keypoints_per_individual, cal, options: SolveOptions, markers: list[str]) -> np.ndarray:
    """(I, N, M, 3): each individual's detections (one Keypoints a camera) solved alone."""
    out = []
    for kps in keypoints_per_individual:
        r = solve(kps, cal, options)
        if list(r.markers) != list(markers):
            raise RuntimeError(f"the solve's markers {r.markers} are not the run's {markers}")
        out.append(r.positions)
    return np.stack(out)


def per_track_points(tracks, k: int) -> np.ndarray:
    """(C, N, M, 2) slot ``k`` of every camera, points below the likelihood threshold NaN."""
    pts = np.stack([t.xy[:, k] for t in tracks]).copy()
    lik = np.stack([t.likelihood[:, k] for t in tracks])
    pts[lik < THRESHOLD] = np.nan
    return pts


def simulated_swaps(owner: np.ndarray) -> list[int]:
    """Per camera, the frames in which the tracker swapped two slots."""
    return [int((np.diff(o, axis=0) != 0).any(axis=1).sum()) for o in owner]


def misassigned(slot_owner: list[np.ndarray], run, match: list[int]) -> dict:
    """The 2D detections (a slot with at least 3 points above the threshold) whose individual is not
    their true animal: ``slot_owner`` (C, N, K) the individual of each slot, ``match`` its animal."""
    to_animal = np.array([*match, -1])  # individual -1 (none) maps to the last entry
    total = wrong = none = 0
    for t, o, truth in zip(run.tracks, slot_owner, run.owner):
        present = ((t.likelihood >= THRESHOLD) & np.isfinite(t.xy).all(-1)).sum(-1) >= 3
        animal = to_animal[np.where(o >= 0, o, len(match))]
        total += int(present.sum())
        none += int((present & (o < 0)).sum())
        wrong += int((present & (o >= 0) & (animal != truth)).sum())
    return {"detections": total, "wrong": wrong, "unassigned": none, "wrong_share": wrong / max(total, 1),
            "unassigned_share": none / max(total, 1)}


def judge(estimates: np.ndarray, run, seconds: float) -> dict:
    """group_error of one method's individuals, each animal's error by the animal's index."""
    g = group_error(estimates, run.positions, run.markers)
    matched = [i for i in range(len(g.match)) if g.match[i] >= 0]
    by_animal = {g.match[i]: g.errors[i] for i in matched}
    animals = []
    for a in range(run.animals):
        e = by_animal.get(a)
        animals.append({"animal": a, "individual": next((i for i in matched if g.match[i] == a), None),
                        "mean_mm": e.mean_mm if e else float("nan"), "median_mm": e.median_mm if e else float("nan"),
                        "p90_mm": e.p90_mm if e else float("nan"), "coverage": e.coverage if e else 0.0})
    return {"individuals": int(estimates.shape[0]), "match": g.match, "switches": g.switches,
            "animal_frames": g.animal_frames, "switches_per_10k": g.switches_per_10k, "animals": animals,
            "seconds": seconds}


def one_group(cal, cgroup, animals: int, frames: int, seed: int, verbose: bool = True) -> dict:
    run = simulate_group(cal, animals=animals, frames=frames, fps=FPS, seed=seed)
    markers = run.markers
    out: dict = {"animals": animals, "seed": seed, "frames": run.frames}

    t0 = time.perf_counter()
    ids = assign(run.tracks, cal, likelihood_threshold=THRESHOLD)
    t_assign = time.perf_counter() - t0
    ours = solve_each(ids.keypoints, cal, fte(run.fps), markers)
    t_ours = time.perf_counter() - t0

    t0 = time.perf_counter()
    ours_tri = solve_each(ids.keypoints, cal, tri(run.fps), markers)
    t_ours_tri = time.perf_counter() - t0 + t_assign

    truth = run.true_tracks()
    slots = [[t.slot(k) for t in truth] for k in range(animals)]
    t0 = time.perf_counter()
    oracle = solve_each(slots, cal, fte(run.fps), markers)
    t_oracle = time.perf_counter() - t0
    t0 = time.perf_counter()
    oracle_tri = solve_each(slots, cal, tri(run.fps), markers)
    t_oracle_tri = time.perf_counter() - t0

    t0 = time.perf_counter()
    per_track = np.stack([h.anipose_triangulate(cgroup, per_track_points(run.tracks, k))
                          for k in range(run.tracks[0].slots)])
    t_per_track = time.perf_counter() - t0

    found = len(ids.names)
    out["identity"] = {**ids.to_dict(), "found": found, "found_equals_animals": found == animals,
                       "simulated_swaps": dict(zip(cal.names, simulated_swaps(run.owner)))}
    out["timing"] = {"assign_s": t_assign, "ours_s": t_ours, "assign_fps": run.frames / t_assign,
                     "ours_fps": run.frames / t_ours}
    out["methods"] = {
        "ours": judge(ours, run, t_ours), "ours-tri": judge(ours_tri, run, t_ours_tri),
        "oracle": judge(oracle, run, t_oracle), "oracle-tri": judge(oracle_tri, run, t_oracle_tri),
        "per-track": judge(per_track, run, t_per_track)}
    m = out["methods"]
    slots_as_given = [np.broadcast_to(np.arange(t.slots), t.xy.shape[:2]) for t in run.tracks]
    out["detections"] = {"tracker": misassigned(slots_as_given, run, m["per-track"]["match"]),
                         "assign": misassigned(ids.slot_owner, run, m["ours"]["match"])}
    ratios = []
    for a in range(animals):
        o, r = out["methods"]["ours"]["animals"][a], out["methods"]["oracle"]["animals"][a]
        ratios.append({"animal": a, "mean": _ratio(o["mean_mm"], r["mean_mm"]),
                       "median": _ratio(o["median_mm"], r["median_mm"])})
    out["ratio_ours_oracle"] = ratios
    if verbose:
        print(f"  {animals} animals, seed {seed}: found {found}, assign {t_assign:.2f} s, ours {t_ours:.2f} s; "
              + ", ".join(f"{name} {m[name]['switches']} switches" for name in METHODS)
              + "; ours/oracle mean " + ", ".join(f"{r['mean']:.3f}" for r in ratios), flush=True)
    return out


def _ratio(a: float, b: float) -> float:
    return a / b if np.isfinite(a) and np.isfinite(b) and b > 0 else float("inf")


def summarise(runs: list[dict]) -> dict:
    pooled = {}
    for name in METHODS:
        sw = sum(r["methods"][name]["switches"] for r in runs)
        af = sum(r["methods"][name]["animal_frames"] for r in runs)
        means = [a["mean_mm"] for r in runs for a in r["methods"][name]["animals"]]
        medians = [a["median_mm"] for r in runs for a in r["methods"][name]["animals"]]
        pooled[name] = {"switches": sw, "animal_frames": af, "switches_per_10k": 1e4 * sw / max(af, 1),
                        "mean_of_animal_means_mm": float(np.mean(means)), "worst_animal_mean_mm": float(np.max(means)),
                        "median_of_animal_medians_mm": float(np.median(medians)),
                        "worst_animal_median_mm": float(np.max(medians))}
    detections = {}
    for who in ("tracker", "assign"):
        total = sum(r["detections"][who]["detections"] for r in runs)
        wrong = sum(r["detections"][who]["wrong"] for r in runs)
        none = sum(r["detections"][who]["unassigned"] for r in runs)
        detections[who] = {"detections": total, "wrong": wrong, "unassigned": none,
                           "wrong_share": wrong / max(total, 1), "unassigned_share": none / max(total, 1)}
    mean_ratios = [x["mean"] for r in runs for x in r["ratio_ours_oracle"]]
    median_ratios = [x["median"] for r in runs for x in r["ratio_ours_oracle"]]
    worst = max(mean_ratios)
    sw = pooled["ours"]["switches_per_10k"]
    return {"pooled": pooled, "detections": detections, "worst_ratio_mean": worst,
            "worst_ratio_median": max(median_ratios),
            "found_equals_animals_all": all(r["identity"]["found_equals_animals"] for r in runs),
            "targets": {"ratio": {"target": TARGET_RATIO, "worst": worst, "met": bool(worst <= TARGET_RATIO)},
                        "switches_per_10k": {"target": TARGET_SWITCHES, "pooled": sw,
                                             "met": bool(sw <= TARGET_SWITCHES)}}}


def print_tables(runs: list[dict], summary: dict) -> None:
    print("\n## 3D identity switches per run\n")
    print(h.markdown_table(
        ["animals", "seed", "method", "individuals", "switches", "animal-frames", "per 10k", "seconds"],
        [[r["animals"], r["seed"], name, m["individuals"], m["switches"], m["animal_frames"], m["switches_per_10k"],
          m["seconds"]] for r in runs for name, m in r["methods"].items()]))

    print("\n## 3D error per animal, mm (mean / median)\n")
    rows = []
    for r in runs:
        for a in range(r["animals"]):
            cells = []
            for name in METHODS:
                e = r["methods"][name]["animals"][a]
                cells += [e["mean_mm"], e["median_mm"]]
            x = r["ratio_ours_oracle"][a]
            rows.append([r["animals"], r["seed"], a + 1, *cells, x["mean"], x["median"]])
    print(h.markdown_table(["animals", "seed", "animal", *[f"{n} {s}" for n in METHODS for s in ("mean", "median")],
                            "ours/oracle mean", "ours/oracle median"], rows))

    print("\n## Identity and time\n")
    print(h.markdown_table(
        ["animals", "seed", "frames", "found", "found = animals", "2D swaps simulated", "2D switches corrected",
         "detections wrong as tracked %", "wrong after assign %", "unassigned %", "assign s", "assign frames/s",
         "ours s", "ours frames/s"],
        [[r["animals"], r["seed"], r["frames"], r["identity"]["found"], r["identity"]["found_equals_animals"],
          sum(r["identity"]["simulated_swaps"].values()), sum(r["identity"]["switches_corrected"].values()),
          100 * r["detections"]["tracker"]["wrong_share"], 100 * r["detections"]["assign"]["wrong_share"],
          100 * r["detections"]["assign"]["unassigned_share"],
          r["timing"]["assign_s"], r["timing"]["assign_fps"], r["timing"]["ours_s"], r["timing"]["ours_fps"]]
         for r in runs]))

    print("\n## Pooled over all runs\n")
    print(h.markdown_table(
        ["method", "switches", "animal-frames", "per 10k", "mean of animal means mm", "worst animal mean mm",
         "median of animal medians mm", "worst animal median mm"],
        [[name, p["switches"], p["animal_frames"], p["switches_per_10k"], p["mean_of_animal_means_mm"],
          p["worst_animal_mean_mm"], p["median_of_animal_medians_mm"], p["worst_animal_median_mm"]]
         for name, p in summary["pooled"].items()]))

    t = summary["targets"]
    print("\n## Targets\n")
    print(h.markdown_table(
        ["criterion", "value", "target", "met"],
        [["worst ours/oracle mean error, over animals and runs", t["ratio"]["worst"], f"<= {TARGET_RATIO}",
          t["ratio"]["met"]],
         ["worst ours/oracle median error (for reference)", summary["worst_ratio_median"], "-", "-"],
         ["ours switches per 10k animal-frames, pooled", t["switches_per_10k"]["pooled"], f"<= {TARGET_SWITCHES}",
          t["switches_per_10k"]["met"]],
         ["2D detections on the wrong animal after assign, pooled %", 100 * summary["detections"]["assign"][
             "wrong_share"], f"(as tracked: {100 * summary['detections']['tracker']['wrong_share']:.1f} %)", "-"],
         ["individuals found = animals, every run", summary["found_equals_animals_all"], "True",
          summary["found_equals_animals_all"]]]))


def warm_up(cal, cgroup) -> None:
    """The one-time compiles (numba kernels, jax's triangulate), untimed."""
    one_group(cal, cgroup, animals=2, frames=60, seed=99, verbose=False)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--frames", type=int, default=3000)
    ap.add_argument("--animals", type=int, nargs="+", default=[2, 3], help="group sizes")
    ap.add_argument("--quick", action="store_true", help="one seed, 600 frames: check that it runs")
    ap.add_argument("--out", default="group", help="bench/results/OUT.json")
    args = ap.parse_args()
    if args.quick:
        args.seeds, args.frames = args.seeds[:1], 600
    warnings.filterwarnings("ignore")  # the solves' noise advice, aniposelib's notices

    cal = ring_rig(4)
    cgroup = h.anipose_group(cal)
    info = h.machine()
    print(f"# Multi-animal identity: ring of {len(cal)} cameras, {args.frames} frames at {FPS:g} fps, groups of "
          f"{', '.join(map(str, args.animals))}, seeds {', '.join(map(str, args.seeds))}; {info['cpu']}, "
          f"{info['cores']} cores, load {info['load_average'][0]:.1f}", flush=True)
    warm_up(cal, cgroup)

    t0 = time.perf_counter()
    runs = [one_group(cal, cgroup, animals, args.frames, seed) for animals in args.animals for seed in args.seeds]
    wall = time.perf_counter() - t0
    summary = summarise(runs)
    print_tables(runs, summary)

    protocol = {"rig": cal.source, "cameras": cal.names, "fps": FPS, "frames": args.frames, "animals": args.animals,
                "seeds": args.seeds, "simulator": "simulate_group defaults (2 % swaps per camera-frame, 5 % missing "
                "instances, 5 % missing points, 2 px noise, 2 % confident outliers)",
                "likelihood_threshold": THRESHOLD, "ours": "assign (individuals found) + fte points per individual",
                "ours-tri": "assign + tri per individual", "oracle": "fte points per true animal",
                "oracle-tri": "tri per true animal",
                "per-track": "aniposelib CameraGroup.triangulate per 2D slot name"}
    path = h.save(args.out, {"machine": info, "load_average_end": list(os.getloadavg()), "wall_s": wall,
                             "args": {k: v for k, v in vars(args).items()}, "protocol": protocol,
                             "summary": summary, "runs": runs})
    print(f"\nwrote {path} ({wall:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
