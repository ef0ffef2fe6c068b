"""Benchmark: fleet physics + uncertainty against the number of sensors (issue #27).

Run:  python benchmarks/bench_fleet.py [--sensors 1 10 100 1000] [--rows 5000] [--full 1000]
      python benchmarks/bench_fleet.py --network --sensors 1 10 40 [--rows 5000] [--epochs 20]

For each N, a separate process simulates N sensors of --rows rows (core/simulate_fleet.py, not timed) and times
the batched fit with its covariance (fit_fleet), the input-noise estimate and the exact physics uncertainty of
every row (fleet_uncertainty): a first call (compilation included) and a second call (compiled). Peak memory is
the process's peak resident set (ru_maxrss, simulation included). --full N also times the whole
`bayesmag fleet configs/fleet_simulated.toml` command with N sensors (sensor folders, report, figures).
--network times the fleet's residual-network stage instead: every sensor's network (3 axes) trained in one
compiled batch (core/network_batch.fit_residual_networks, --batch sensors per call, a fixed --epochs: patience =
epochs, so every N does the same work per sensor), first call and compiled call, against the same networks
trained one sensor at a time by the single-run code (core/network.fit_residual_network, compiled, up to 3 sensors
timed and scaled) -- the cost per sensor of each.
Prints a markdown table (docs/benchmarks.md).
"""

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def one(n_sensors: int, rows: int, batch: int) -> dict:
    import numpy as np
    from bayesmag._src.core.fleet_fit import FleetData, fit_fleet, fleet_input_noise, fleet_uncertainty
    from bayesmag._src.core.physics import PhysicsModel
    from bayesmag._src.core.simulate_fleet import simulate_fleet

    recs, truth = simulate_fleet(n_sensors, rows, seed=0, n_defective=min(5, n_sensors // 20))
    fleet = FleetData.from_recordings(recs, truth.ids)
    del recs
    model = PhysicsModel.paper(t0=25.0)
    out = {"n_sensors": n_sensors, "rows": rows}
    for label in ("first", "second"):
        t, c = time.perf_counter(), time.process_time()
        fit = fit_fleet(fleet, model, batch_size=batch)
        t_fit = time.perf_counter() - t
        uq = fleet_uncertainty(fit, fleet, fleet_input_noise(fleet), batch_size=min(batch, 16))
        out[label] = {"fit_s": t_fit, "total_s": time.perf_counter() - t, "cpu_s": time.process_time() - c}
        assert fit.converged.all() and np.isfinite(uq.aleatoric).all()
        del uq
    out["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    return out


def network(n_sensors: int, rows: int, batch: int, epochs: int) -> dict:
    """Batched residual networks of ``n_sensors`` sensors against one-at-a-time training (see the docstring)."""
    from bayesmag._src.core.data import make_split
    from bayesmag._src.core.fleet_fit import FleetData, fit_fleet, fleet_predict
    from bayesmag._src.core.network import NetworkSpec, fit_residual_network
    from bayesmag._src.core.network_batch import fit_residual_networks
    from bayesmag._src.core.physics import PhysicsModel
    from bayesmag._src.core.predictor import network_inputs
    from bayesmag._src.core.simulate_fleet import simulate_fleet

    recs, truth = simulate_fleet(n_sensors, rows, seed=0, n_defective=0, rows_spread=0.2)   # as fleet_simulated
    trains = [r.subset(make_split(r, kind="time_blocks", test_fraction=0.2, seed=0).train) for r in recs]
    fleet = FleetData.from_recordings(trains, truth.ids)
    pred = fleet_predict(fit_fleet(fleet, PhysicsModel.paper(t0=25.0), batch_size=64), fleet)
    xs = [network_inputs(t) for t in trains]
    rs = [t.b_ref - pred[i, :t.n] for i, t in enumerate(trains)]
    groups = [t.run for t in trains]
    spec = NetworkSpec(hidden_layers=2, width=32, batch_size=64, max_epochs=epochs, patience=epochs,
                       validation="time_blocks")
    out = {"n_sensors": n_sensors, "rows": rows, "epochs": epochs, "network": "2 x 32, minibatch 64"}
    for label in ("first", "second"):
        t, c = time.perf_counter(), time.process_time()
        fit_residual_networks(xs, rs, spec, groups=groups, batch_size=batch)
        out[label] = {"total_s": time.perf_counter() - t, "cpu_s": time.process_time() - c}
    k = min(3, n_sensors)
    t, c = time.perf_counter(), time.process_time()
    for i in range(k):               # as a loop over sensors would: every new recording length compiles again
        fit_residual_network(xs[i], rs[i], spec, groups=groups[i])
    out["single_per_sensor"] = {"total_s": (time.perf_counter() - t) / k, "cpu_s": (time.process_time() - c) / k}
    t, c = time.perf_counter(), time.process_time()
    fit_residual_network(xs[0], rs[0], spec, groups=groups[0])          # that length compiled already
    out["single_compiled"] = {"total_s": time.perf_counter() - t, "cpu_s": time.process_time() - c}
    import jax
    out["device"] = str(jax.devices()[0])
    out["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    return out


def detect(seeds: int, n_sensors: int, rows: int, batch: int) -> None:
    """For each seed: the planted units, those flagged (|robust z| > 7 or a limit), and the largest |z| of a clean unit."""
    import tempfile as tf
    import numpy as np
    from bayesmag._src.app.fleet import fleet_config_from_dict, run_fleet
    print("| seed | sensors x rows | planted | flagged exactly | largest max-|z| of a clean unit | smallest of a planted unit |")
    print("|---|---|---|---|---|---|")
    for seed in range(seeds):
        raw = {"fleet": {"source": "simulated", "batch_size": batch, "sensor_folders": False, "figures": False,
                         "simulate": {"n_sensors": n_sensors, "n_rows": rows, "seed": seed, "n_defective": 5}}}
        s = run_fleet(fleet_config_from_dict(raw), Path(tf.mkdtemp()) / "out", progress=False)
        gt = s["ground_truth"]
        z = {x["id"]: x["max_abs_robust_z"] for x in s["sensors"]}
        clean = max(v for k, v in z.items() if k not in gt["defective"])
        bad = min(z[k] for k in gt["defective"])
        print(f"| {seed} | {n_sensors} x {rows} | {len(gt['defective'])} | {gt['exact']} | {clean:.2f} | {bad:.1f} |",
              flush=True)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--sensors", type=int, nargs="*", default=[1, 10, 100, 1000])
    ap.add_argument("--rows", type=int, default=5000)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--full", type=int, default=0, help="also time `bayesmag fleet` with this many sensors")
    ap.add_argument("--one", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--network", action="store_true", help="time the batched residual-network stage instead")
    ap.add_argument("--epochs", type=int, default=20, help="--network: epochs per network (no early stopping)")
    ap.add_argument("--detect", type=int, default=0, metavar="SEEDS",
                    help="instead: planted defects vs flagged for seeds 0..SEEDS-1 (--sensors N each, --rows rows)")
    args = ap.parse_args()
    if args.detect:
        detect(args.detect, args.sensors[0], args.rows, args.batch)
        return
    if args.one:
        print(json.dumps(network(args.one, args.rows, args.batch, args.epochs) if args.network
                         else one(args.one, args.rows, args.batch)))
        return
    rows = []
    for n in args.sensors:
        r = subprocess.run([sys.executable, __file__, "--one", str(n), "--rows", str(args.rows), "--batch",
                            str(args.batch), "--epochs", str(args.epochs)] + ["--network"] * args.network,
                           capture_output=True, text=True, check=True)
        rows.append(json.loads(r.stdout.strip().splitlines()[-1]))
        print(rows[-1], file=sys.stderr)
    if args.network:
        print(f"Device: {rows[0]['device']}; {rows[0]['network']}, {args.epochs} epochs, {args.batch} sensors per "
              f"call; recordings of {int(0.8 * args.rows)}-{args.rows} rows.\n")
        print("| sensors | batched, first call (compile incl.): wall / CPU (s) | batched, compiled: wall / CPU (s) | "
              "per sensor, batched compiled: wall / CPU (s) | per sensor, one at a time (each length compiles): "
              "wall / CPU (s) | one sensor alone, compiled: wall / CPU (s) | peak RSS (GB) |")
        print("|---|---|---|---|---|---|---|")
        for r in rows:
            f, s, o, c = r["first"], r["second"], r["single_per_sensor"], r["single_compiled"]
            print(f"| {r['n_sensors']} | {f['total_s']:.1f} / {f['cpu_s']:.1f} | {s['total_s']:.2f} / "
                  f"{s['cpu_s']:.2f} | {s['total_s'] / r['n_sensors']:.3f} / {s['cpu_s'] / r['n_sensors']:.3f} | "
                  f"{o['total_s']:.2f} / {o['cpu_s']:.2f} | {c['total_s']:.3f} / {c['cpu_s']:.3f} | "
                  f"{r['peak_rss_gb']:.2f} |")
        return
    print("| sensors x rows | first call: wall / CPU (s, compile incl.) | compiled call: wall / CPU (s) | "
          "per sensor, compiled: wall / CPU (ms) | peak RSS (GB) |")
    print("|---|---|---|---|---|")
    for r in rows:
        f, s = r["first"], r["second"]
        print(f"| {r['n_sensors']} x {r['rows']} | {f['total_s']:.2f} / {f['cpu_s']:.2f} | {s['total_s']:.2f} / "
              f"{s['cpu_s']:.2f} | {1e3 * s['total_s'] / r['n_sensors']:.1f} / {1e3 * s['cpu_s'] / r['n_sensors']:.1f} | "
              f"{r['peak_rss_gb']:.2f} |")
    if args.full:
        out = Path(tempfile.mkdtemp(prefix="bench_fleet_")) / "out"
        cmd = [sys.executable, "-m", "bayesmag._src.app.cli", "fleet", str(ROOT / "configs/fleet_simulated.toml"),
               "--out", str(out), "--no-progress", "--set", f"fleet.simulate.n_sensors={args.full}"]
        t = time.perf_counter()
        r = subprocess.run(["/usr/bin/time", "-f", "%M %U %S"] + cmd, capture_output=True, text=True, check=True)
        wall = time.perf_counter() - t
        s = json.loads((out / "fleet.json").read_text())
        m, u, sy = r.stderr.strip().splitlines()[-1].split()
        peak = int(m) / 2**20
        print(f"\n`bayesmag fleet` with {args.full} sensors: {wall:.1f} s wall, {float(u) + float(sy):.1f} s CPU "
              f"({s['timings']}), peak RSS {peak:.2f} GB; "
              f"flagged {s['n_fail']}, ground truth exact: {s['ground_truth']['exact']}")


if __name__ == "__main__":
    main()
