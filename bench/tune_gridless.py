"""Scratch benchmark for the gridless solver (fixed seeds; not collected by pytest).

Usage: .venv/bin/python -m bench.tune_gridless --k 1 4 8 --snr 30 --trials 50 [--model power]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.optimize import linear_sum_assignment

from app.vlp.crlb import aggregated_crlb
from app.vlp.fingerprints import build_fingerprint
from app.vlp.layout import Grid, Layout, Led, Receiver, Room
from app.vlp.measurements import measurement_from_amplitudes
from app.vlp.presets import paper_layout
from app.vlp.simulation import noise_std_for_snr, noisy_amplitudes, random_positions
from app.vlp.solvers.gridless import GridlessOptions, GridlessSolver


def matched_error(truth: np.ndarray, est: np.ndarray) -> float:
    """Mean Euclidean error after Hungarian matching."""
    cost = np.linalg.norm(truth[:, None, :] - est[None, :, :], axis=2)
    rows, cols = linear_sum_assignment(cost)
    return float(cost[rows, cols].mean())


def other_rooms() -> dict[str, Layout]:
    """Rooms that are not the paper room (irregular LEDs, mixed angles, other sizes)."""
    gen = np.random.default_rng(7)
    rx = Receiver(area=1e-4, fov_deg=70.0, filter_gain=1.0, refractive_index=1.5)
    leds = tuple(
        Led(float(x), float(y), 3.2, float(a), 1.0)
        for x, y, a in zip(
            gen.uniform(0.3, 5.7, 12),
            gen.uniform(0.3, 4.7, 12),
            gen.choice([45, 60, 70], 12),
            strict=True,
        )
    )
    irregular = Layout(Room(6.0, 5.0, 3.2), Grid(0.25, 0.8), leds, rx, "irregular")
    leds2 = tuple(
        Led(1.0 + 2.0 * i, 1.0 + 2.0 * j, 4.0, 50.0, 1.0 + 0.5 * ((i + j) % 2))
        for i in range(4)
        for j in range(3)
    )
    hall = Layout(
        Room(8.0, 6.0, 4.0), Grid(0.2, 1.0), leds2, Receiver(1e-4, 60.0, 1.0, 1.5), "hall"
    )
    return {"paper": paper_layout(), "irregular": irregular, "hall": hall}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--k", type=int, nargs="+", default=[1, 4, 8])
    parser.add_argument("--snr", type=float, nargs="+", default=[30.0])
    parser.add_argument("--trials", type=int, default=50)
    parser.add_argument("--model", default="correlation")
    parser.add_argument("--room", default="paper")
    parser.add_argument("--free", action="store_true", help="free weights")
    parser.add_argument("--plain", action="store_true", help="no whitening")
    parser.add_argument("--inner", type=int, default=GridlessOptions.inner_iter)
    parser.add_argument("--rounds", type=int, default=GridlessOptions.whiten_rounds)
    parser.add_argument("--crb", action="store_true", help="also the aggregated CRB")
    parser.add_argument("--passes", type=int, default=GridlessOptions.relocate_passes)
    parser.add_argument("--restarts", type=int, default=GridlessOptions.restarts)
    parser.add_argument("--unknown", action="store_true", help="estimate K")
    args = parser.parse_args()
    layout = other_rooms()[args.room]
    fp = build_fingerprint(layout)
    opts = GridlessOptions(
        free_weights=args.free,
        whiten=not args.plain,
        inner_iter=args.inner,
        whiten_rounds=args.rounds,
        relocate_passes=args.passes,
        restarts=args.restarts,
    )
    solver = GridlessSolver(fp, args.model, opts)
    for snr in args.snr:
        sigma = noise_std_for_snr(fp, snr)
        for k in args.k:
            errs, times, counts, iters, cpu, bounds = [], [], [], [], [], []
            for trial in range(args.trials):
                gen = np.random.default_rng(1000 * k + trial)
                truth = random_positions(layout, k, rng=gen)
                amps = noisy_amplitudes(layout, truth, sigma, rng=gen)
                meas = measurement_from_amplitudes(amps, args.model, layout.n_leds)
                start, start_cpu = time.perf_counter(), time.process_time()
                sol = solver.solve(meas, None if args.unknown else k)
                times.append(time.perf_counter() - start)
                cpu.append(time.process_time() - start_cpu)
                counts.append(sol.n_targets == k)
                iters.append(sol.n_iter)
                if args.crb:
                    bounds.append(aggregated_crlb(layout, truth, sigma, args.model).mean)
                if sol.n_targets == k:
                    errs.append(matched_error(truth, sol.positions))
            e = np.array(errs) * 100
            print(
                f"{args.room} {args.model} snr={snr:g} K={k}: mean {e.mean():.2f} cm "
                f"median {np.median(e):.2f} p90 {np.percentile(e, 90):.2f} "
                f"count-ok {np.mean(counts):.2f} "
                + (
                    f"crb mean {100 * np.mean(bounds):.2f} median {100 * np.median(bounds):.2f} "
                    if bounds
                    else ""
                )
                + f"time median {1000 * np.median(times):.2f} ms "
                + f"(cpu {1000 * np.median(cpu):.2f}) iters {np.median(iters):.0f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
