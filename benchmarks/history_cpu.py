"""Server CPU per GET of the history mix, two or more versions of the code paired request by
request (``python -m benchmarks.history_cpu REV REV ...``).

The history benchmark's latencies on this shared 2-core machine move by 10-30 % between blocks
of one run, more than most changes to a request's cost. Here every version (a git revision,
checked out with ``git archive`` into a temporary directory) serves one seeded SQLite or
PostgreSQL history at the same time, and each request of each of the seven GET kinds of
``benchmarks.history_client.get_mix`` goes to every server in turn (A B C A B C ..., reversed
every other round), so all of them meet the same machine state. A server's CPU per request
is its threads' run time (``/proc/<pid>/task/*/schedstat``) over ``--n`` requests of one kind;
on PostgreSQL also its database backends' (told apart by ``application_name``, set through
``PGAPPNAME``), which run on the same cores. The servers' answers are compared on the
warm-up requests; the kinds where they differ (a change of the API) are printed first.

    python -m benchmarks.history_cpu origin/main HEAD                 # SQLite, 1,000 calibrations
    python -m benchmarks.history_cpu --backend postgresql 2e8b576 HEAD

Requests go only to 127.0.0.1; servers and temporary directories are removed on every exit.
"""

from __future__ import annotations

import argparse
import contextlib
import http.client
import os
import random
import secrets
import subprocess
import sys
import tempfile
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from sqlalchemy import create_engine, text

from benchmarks.history_client import get_mix
from benchmarks.service_history import _deep_cursor, _env, databases, seed
from service.serving.local import ServeOptions, local_service

REPO = Path(__file__).resolve().parent.parent


def checkout(rev: str, into: Path) -> Path:
    """The tracked files of ``rev`` in ``into`` (``git archive``)."""
    into.mkdir(parents=True)
    archive = subprocess.run(["git", "-C", str(REPO), "archive", rev], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    return into


def cpu_s(pid: int) -> float:
    """Run time of all of the process's threads so far, seconds."""
    total = 0
    for tid in os.listdir(f"/proc/{pid}/task"):
        with contextlib.suppress(FileNotFoundError):
            total += int(Path(f"/proc/{pid}/task/{tid}/schedstat").read_text().split()[0])
    return total / 1e9


#: CPU per request, ms: by revision, by GET kind, one figure per round.
Figures = dict[str, dict[str, list[float]]]


def backends_cpu_s(engine: Any, app: str) -> float:
    """Run time so far of the PostgreSQL backends serving connections named ``app``."""
    with engine.connect() as conn:
        pids = conn.execute(text("SELECT pid FROM pg_stat_activity WHERE application_name = "
                                 ":app"), {"app": app}).scalars().all()
    return sum(cpu_s(pid) for pid in pids)


def measure(revs: list[str], backend: str, calibrations: int, rounds: int,
            n: int) -> tuple[Figures, Figures]:
    """Serve one seeded history with each revision at once and send them the GET mix by
    turns; the server's CPU per request and its database backends' (PostgreSQL; else
    empty)."""
    key = secrets.token_urlsafe(24)
    auth = {"Authorization": f"Bearer {key}"}
    names = labels(revs)
    per: Figures = defaultdict(lambda: defaultdict(list))
    per_db: Figures = defaultdict(lambda: defaultdict(list))
    with tempfile.TemporaryDirectory(prefix="cellcal-history-cpu-") as tmp_dir, \
            databases(backend, Path(tmp_dir), 1) as (url,), contextlib.ExitStack() as stack:
        tmp = Path(tmp_dir)
        cal_ids = seed(url, first=0, count=calibrations, stations=20)
        env = {**_env(), "CELLCAL_DATABASE_URL": url, "CELLCAL_CELL": "cell-00"}
        apps = {name: f"history-cpu-{k}" for k, name in enumerate(names)}
        servers = {name: stack.enter_context(local_service(
            tmp / f"data-{k}", key, ServeOptions(env={**env, "PGAPPNAME": apps[name]},
                                                 cwd=checkout(rev, tmp / f"src-{k}"))))
            for k, (name, rev) in enumerate(zip(names, revs, strict=True))}
        engine = create_engine(url) if backend == "postgresql" else None
        stack.callback(lambda: engine is not None and engine.dispose())

        def db_cpu_s(name: str) -> float:
            return 0.0 if engine is None else backends_cpu_s(engine, apps[name])
        run_ids = [run["id"] for run in httpx.get(f"{servers[names[0]].url}/runs?limit=500",
                                                  headers=auth, timeout=60).json()]
        mix = get_mix(cal_ids, run_ids, _deep_cursor(url, cal_ids))
        conns = {name: http.client.HTTPConnection("127.0.0.1", int(svc.url.rsplit(":", 1)[1]))
                 for name, svc in servers.items()}

        def get(name: str, path: str) -> bytes:
            conns[name].request("GET", path, headers=auth)
            answer = conns[name].getresponse()
            body = answer.read()
            if answer.status != 200:
                raise RuntimeError(f"{name} {path}: {answer.status} {body[:200]!r}")
            return body

        rng = random.Random(0)
        differ = warm_up(get, names, mix, rng)
        if differ:  # an API change: the comparison is of different work for these kinds
            print(f"the revisions answer differently: {', '.join(differ)}", flush=True)
        for r in range(rounds):
            for kind, path_of in mix:
                before = {name: cpu_s(svc.proc.pid) for name, svc in servers.items()}
                db_before = {name: db_cpu_s(name) for name in names}
                for path in [path_of(rng) for _ in range(n)]:
                    for name in names[::-1 if r % 2 else 1]:
                        get(name, path)
                for name, svc in servers.items():
                    per[name][kind].append(1e3 * (cpu_s(svc.proc.pid) - before[name]) / n)
                    if engine is not None:
                        per_db[name][kind].append(1e3 * (db_cpu_s(name) - db_before[name]) / n)
            print(f"round {r + 1} done (load average {os.getloadavg()[0]:.1f})", flush=True)
    return per, per_db


def warm_up(get: Callable[[str, str], bytes], names: list[str], mix: list[Any],
            rng: random.Random) -> list[str]:
    """Send every server 20 requests of each kind; the kinds whose answers differ."""
    differ = {kind for kind, path_of in mix for _ in range(20)
              if len({get(name, path) for path in [path_of(rng)] for name in names}) != 1}
    return sorted(differ)


def labels(revs: list[str]) -> list[str]:
    """A name per server: the revision, numbered where it is given more than once (an A/A
    control of the pairing itself)."""
    return [rev if revs.count(rev) == 1 else f"{rev}#{k + 1}" for k, rev in enumerate(revs)]


def report(per: Figures, names: list[str]) -> None:
    """Mean CPU per request of each kind and server, and its ratio to the first one."""
    revs, ref = names, names[0]
    print(f"{'request':34}" + "".join(f"{rev[:16]:>17}" for rev in revs))

    def row(name: str, of: dict[str, float]) -> None:
        print(f"{name:34}" + "".join(f"{of[rev]:8.2f} {of[rev] / of[ref]:6.3f}x" for rev in revs))

    for kind in per[ref]:
        row(kind, {rev: float(np.mean(per[rev][kind])) for rev in revs})
    row("mean over the kinds", {rev: float(np.mean([np.mean(v) for v in per[rev].values()]))
                                for rev in revs})
    for rev in revs:
        rounds = np.mean(list(per[rev].values()), axis=0)
        print(f"  {rev[:16]} per round: " + " ".join(f"{x:.2f}" for x in rounds))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("revs", nargs="+", help="git revisions; the first is the reference")
    parser.add_argument("--backend", choices=("sqlite", "postgresql"), default="sqlite")
    parser.add_argument("--calibrations", type=int, default=1000)
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--n", type=int, default=100, help="requests per kind and round")
    args = parser.parse_args()
    per, per_db = measure(args.revs, args.backend, args.calibrations, args.rounds, args.n)
    print(f"\nserver CPU per request, ms (mean of {args.rounds} rounds of {args.n}), "
          f"{args.backend}, {args.calibrations:,} calibrations; ratio to {args.revs[0]}")
    report(per, labels(args.revs))
    if per_db:
        print("\nits PostgreSQL backends' CPU per request, ms")
        report(per_db, labels(args.revs))
    return 0


if __name__ == "__main__":
    sys.exit(main())
