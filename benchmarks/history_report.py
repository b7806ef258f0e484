"""The history benchmark's report (``benchmarks.service_history``): the table, the verdicts
and the figure.

Each (database, client, history size) was measured in several blocks, the sizes by turns.
The verdict is on the pooled latencies of all blocks of a size (p99 of thousands of requests,
not of a few hundred), and the spread over the blocks is printed beside it: the p99 of each
block and the growth of each round's pair, so a figure's noise is seen, not guessed.
"""

from __future__ import annotations

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from benchmarks import results_dir
from benchmarks.service_history import (
    CLIENTS,
    LISTENERS,
    TARGET_GROWTH,
    TARGET_P99_MS,
    Latencies,
    Level,
)

OUT = results_dir()


def _ms(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values) * 1e3, q)) if values else float("nan")


def _pooled(blocks: list[Level]) -> Latencies:
    """The latencies of ``blocks`` together."""
    out = Latencies()
    for block in blocks:
        for kind, values in block.latencies.by_kind.items():
            out.by_kind.setdefault(kind, []).extend(values)
        for kind, count in block.latencies.errors.items():
            out.errors[kind] = out.errors.get(kind, 0) + count
    return out


def _gets(latencies: Latencies) -> list[float]:
    return [x for k, v in latencies.by_kind.items() if k.startswith("GET") for x in v]


def _span(values: list[float], fmt: str = "{:.1f}") -> str:
    return f"{fmt.format(min(values))}-{fmt.format(max(values))}"


def report(levels: list[Level]) -> bool:
    """Print the table and the verdicts, draw the figure; True if every target is met with
    every client."""
    kinds = sorted({k for lv in levels for k in lv.latencies.by_kind})
    groups: dict[tuple[str, str, int], list[Level]] = {}
    for lv in levels:
        groups.setdefault((lv.backend, lv.client, lv.calibrations), []).append(lv)
    print(f"\n{'database':10} {'client':7} {'calibrations':>12} {'request':34} {'n':>6} "
          f"{'p50 ms':>8} {'p99 ms':>8} {'p99 per block':>14} {'non-2xx':>7}")
    for (backend, client, calibrations), blocks in groups.items():
        pooled = _pooled(blocks)
        for kind in kinds:
            got = pooled.by_kind.get(kind, [])
            per_block = [_ms(b.latencies.by_kind.get(kind, []), 99) for b in blocks]
            print(f"{backend:10} {client:7} {calibrations:>12,} {kind:34} {len(got):>6} "
                  f"{_ms(got, 50):>8.1f} {_ms(got, 99):>8.1f} {_span(per_block):>14} "
                  f"{pooled.errors.get(kind, 0):>7}")
    ok = True
    for backend, client in dict.fromkeys((b, c) for b, c, _ in groups):
        small, large = ((size, blocks) for (b, c, size), blocks in groups.items()
                        if (b, c) == (backend, client))
        ok &= _verdict(backend, client, small, large)
    _plot(groups, kinds)
    return ok


def _verdict(backend: str, client: str, small: tuple[int, list[Level]],
             large: tuple[int, list[Level]]) -> bool:
    """One line per database and client: pooled all-GET p50 / p99 at both sizes, the growth,
    and the spread over the rounds; True if the targets are met."""
    (n_small, b_small), (n_large, b_large) = small, large
    gets_small, gets_large = _gets(_pooled(b_small)), _gets(_pooled(b_large))
    p99_small, p99_large = _ms(gets_small, 99), _ms(gets_large, 99)
    growth = p99_large / p99_small
    met = p99_large < TARGET_P99_MS and growth <= TARGET_GROWTH
    round_small = [_ms(_gets(b.latencies), 99) for b in sorted(b_small, key=lambda b: b.round)]
    round_large = [_ms(_gets(b.latencies), 99) for b in sorted(b_large, key=lambda b: b.round)]
    fewest = min(len(v) for b in (b_small, b_large) for k, v in _pooled(b).by_kind.items()
                 if k.startswith("GET"))
    loads = [b.load_average for b in b_small + b_large]
    print(f"{backend}, {client} client: all GETs p50 / p99 {_ms(gets_small, 50):.1f} / "
          f"{p99_small:.1f} ms at {n_small:,}, {_ms(gets_large, 50):.1f} / {p99_large:.1f} ms "
          f"at {n_large:,} ({growth:.2f}x; {len(gets_small)} / {len(gets_large)} GETs, at "
          f"least {fewest} per GET kind; over {len(b_small)} rounds p99 "
          f"{_span(round_small)} / {_span(round_large)} ms, growth "
          f"{_span([lg / sm for sm, lg in zip(round_small, round_large, strict=True)], '{:.2f}')}"
          f"x; load average {_span(loads)}; CPU per request: server "
          f"{np.mean([b.server_cpu_ms for b in b_small]):.1f} / "
          f"{np.mean([b.server_cpu_ms for b in b_large]):.1f} ms, client "
          f"{np.mean([b.client_cpu_ms for b in b_small]):.1f} / "
          f"{np.mean([b.client_cpu_ms for b in b_large]):.1f} ms): "
          f"{'met' if met else 'NOT met'} (target < {TARGET_P99_MS:g} ms, <= {TARGET_GROWTH}x)")
    return met


def _plot(groups: dict[tuple[str, str, int], list[Level]], kinds: list[str]) -> None:
    """Per database: each request kind's pooled p99 per (size, client), the bars' whiskers
    spanning the blocks' p99s."""
    OUT.mkdir(exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(13, 6), sharey=True)
    backends = list(dict.fromkeys(b for b, _, _ in groups))
    for ax, backend in zip(axes, backends, strict=False):
        mine = [(key, blocks) for key, blocks in groups.items() if key[0] == backend]
        y = np.arange(len(kinds))
        height = 0.8 / len(mine)
        for j, ((_, client, size), blocks) in enumerate(mine):
            pooled = _pooled(blocks)
            p99 = np.array([_ms(pooled.by_kind.get(k, []), 99) for k in kinds])
            per_block = np.array([[_ms(b.latencies.by_kind.get(k, []), 99) for b in blocks]
                                  for k in kinds])
            spread = np.vstack([p99 - per_block.min(axis=1), per_block.max(axis=1) - p99])
            ax.barh(y + height * j, p99, height=height, xerr=np.clip(spread, 0, None),
                    error_kw={"lw": 0.8, "capsize": 2},
                    label=f"{size:,} calibrations, {client} client")
        ax.axvline(TARGET_P99_MS, color="k", ls="--", lw=1, label="target")
        ax.set_yticks(y + 0.4 - height / 2, kinds)
        ax.set_xlabel("p99 latency (ms), all blocks; whiskers: the blocks' p99s")
        ax.set_title(f"{backend}: {CLIENTS} clients, {LISTENERS} SSE listeners")
        ax.legend(loc="lower right", fontsize=8, framealpha=0.9)
    fig.tight_layout()
    fig.savefig(OUT / "service_history.png", dpi=110)
    print(f"wrote {OUT / 'service_history.png'}")
