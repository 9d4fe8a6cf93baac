"""Epoch benchmark: what one cooperation round costs over HTTP, next to one localize.

Starts a real ``vlp serve`` (one process, SQLite, BLAS one thread) on loopback, waits for the
demo (paper) room, and repeats ``--rounds`` times with K terminals at random positions
(seeded, 30 dB): create an epoch, K sequential posts, ``solve``; then the same amplitudes as
one ``localize`` with ``terminals``. Prints the medians of one post, of ``solve``, of the
whole round and of localize.

    python -m bench.epochs [--rounds 20] [--terminals 8]
"""

from __future__ import annotations

import argparse
import functools
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import httpx

from app.vlp.fingerprints import build_fingerprint
from app.vlp.presets import paper_layout
from app.vlp.simulation import noise_std_for_snr, noisy_amplitudes, random_positions
from bench._server import TERMINAL_KEY, live_server, ready_demo_room

_HEADERS = {"X-API-Key": TERMINAL_KEY}


def _timed(call: Callable[[], httpx.Response]) -> tuple[httpx.Response, float]:
    started = time.perf_counter()
    response = call()
    response.raise_for_status()
    return response, time.perf_counter() - started


def _round(
    client: httpx.Client, room_id: str, n_terminals: int, seed: int
) -> tuple[list[float], float, float, float]:
    layout = paper_layout()
    noise_std = noise_std_for_snr(build_fingerprint(layout), 30.0)
    positions = random_positions(layout, n_terminals, rng=seed)
    amplitudes = noisy_amplitudes(layout, positions, noise_std, rng=seed).tolist()
    started = time.perf_counter()
    epoch = client.post(f"/v1/rooms/{room_id}/epochs", json={"window_s": 60}).json()
    base = f"/v1/rooms/{room_id}/epochs/{epoch['id']}"
    posts = []
    for k, row in enumerate(amplitudes):
        post = {"terminal_id": f"t{k}", "amplitudes": row}
        posts.append(_timed(functools.partial(client.post, f"{base}/measurements", json=post))[1])
    solved, solve_s = _timed(lambda: client.post(f"{base}/solve"))
    assert solved.json()["status"] == "solved", solved.text
    round_s = time.perf_counter() - started
    terminals = [{"id": f"t{k}", "amplitudes": row} for k, row in enumerate(amplitudes)]
    body = {"terminals": terminals, "targets": n_terminals}
    _, localize_s = _timed(lambda: client.post(f"/v1/rooms/{room_id}/localize", json=body))
    return posts, solve_s, round_s, localize_s


def main() -> None:
    """Run the benchmark and print the medians."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=20)
    parser.add_argument("--terminals", type=int, default=8)
    args = parser.parse_args()
    posts: list[float] = []
    solves: list[float] = []
    rounds: list[float] = []
    localizes: list[float] = []
    with (
        tempfile.TemporaryDirectory() as tmp,
        live_server(Path(tmp)) as server,
        httpx.Client(base_url=server.url, headers=_HEADERS, timeout=60) as client,
    ):
        room_id = ready_demo_room(server.url)
        _round(client, room_id, args.terminals, seed=10_000)  # warm the caches
        for seed in range(args.rounds):
            post_s, solve_s, round_s, localize_s = _round(client, room_id, args.terminals, seed)
            posts += post_s
            solves.append(solve_s)
            rounds.append(round_s)
            localizes.append(localize_s)

    def median_ms(values: list[float]) -> str:
        return f"{1e3 * statistics.median(values):.1f} ms"

    print(
        f"K={args.terminals}, {args.rounds} rounds: post {median_ms(posts)}, "
        f"solve {median_ms(solves)}, whole round {median_ms(rounds)}; "
        f"localize of the same terminals {median_ms(localizes)}"
    )


if __name__ == "__main__":
    main()
