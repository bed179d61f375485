"""Fault campaign on ``wpot all-vs-all``: SIGKILL at random moments, rerun, compare with an uninterrupted run.

What it measures (issue 22, "Reliability, measured"): the store's contract under crashes. For each execution
mode (inline, ``--jobs 2``, ``--scheduler local --jobs 2``) it

1. runs the command once without interruption on a small generated dataset (the reference);
2. starts the same command on a fresh run folder, kills its whole process group (the coordinator and its
   workers) with SIGKILL after a random delay (uniform between 0 and the reference's wall time, so kills land
   in every phase: reading meshes, spectra, signatures and their cache writes, pairs, commits), restarts it,
   kills it again, ... and after the last kill reruns it to completion;
3. checks the finished store: D(inf) and D(beta) (every beta) equal to the reference's bit for bit (the
   computation is deterministic), no pair committed twice (the ``computations`` table against ``pairs``), no
   failures, and the final command's exit status 0.

It also counts pairs *recomputed* after a kill: pairs that were in flight when the kill came (started, not
committed) and so ran again. Those are allowed (the work of an unfinished pair is lost); committing a pair
twice is not. The count comes from a start log: a ``sitecustomize`` module put on the subprocesses'
``PYTHONPATH`` wraps ``wpot.runs.workers.pair_task`` to append "i j" to a file at every pair start, in the
coordinator and in every worker process (process pool and Dask alike). The instrumentation lives here only;
nothing in wpot knows about it.

Usage::

    python benchmarks/fault_campaign.py                 # 50 kills: 20 inline, 15 --jobs 2, 15 --scheduler local
    python benchmarks/fault_campaign.py --kills 9 --seed 1

Prints one table row per mode: kills, reruns, trials (fresh run folders), final matrices equal, pairs
committed twice, pairs recomputed after a kill, failures, time. A few minutes on 2 CPU cores.
"""
from __future__ import annotations

import argparse
import os
import random
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np

SETTINGS = ["--max-vertices", "60", "--n-eigen", "40", "--n-energies", "40", "--device", "cpu", "--no-progress"]
MODES = {"inline": [], "--jobs 2": ["--jobs", "2"], "--scheduler local": ["--scheduler", "local", "--jobs", "2"]}
SHARE = {"inline": 0.4, "--jobs 2": 0.3, "--scheduler local": 0.3}

SITECUSTOMIZE = textwrap.dedent('''
    """Fault-campaign instrumentation: log every pair start to $WPOT_CAMPAIGN_LOG (benchmarks/fault_campaign.py)."""
    import os
    if os.environ.get("WPOT_CAMPAIGN_LOG"):
        import functools
        import wpot.runs.loop as _p
        _orig = _p._pair_task

        @functools.wraps(_orig)
        def _pair_task(i, j, *args, **kwargs):
            fd = os.open(os.environ["WPOT_CAMPAIGN_LOG"], os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
            try:
                os.write(fd, f"{i} {j}\\n".encode())
            finally:
                os.close(fd)
            return _orig(i, j, *args, **kwargs)

        _p._pair_task = _pair_task
''')


def make_dataset(folder: Path, n_per_class: int = 3) -> Path:
    """Two classes of small meshes (the example surface and a stretched copy), each a different triangulation."""
    from wpot.examples import example_mesh
    from wpot.io import save_mesh
    from wpot.mesh import Mesh

    folder.mkdir(parents=True, exist_ok=True)
    for k in range(n_per_class):
        m = example_mesh(60 + 7 * k, seed=k)
        save_mesh(m, folder / f"blob{k + 1}.off")
        save_mesh(Mesh(m.vertices * np.array([1.8, 0.6, 1.0]), m.faces), folder / f"flat{k + 1}.off")
    return folder


class Campaign:
    """Runs the commands and keeps the per-mode figures."""

    def __init__(self, work: Path, data: Path, hook_dir: Path) -> None:
        self.work, self.data, self.hook_dir = work, data, hook_dir

    def command(self, mode: str, run: Path) -> list[str]:
        return [sys.executable, "-m", "wpot.cli", "all-vs-all", str(self.data), "--out", str(run), *SETTINGS, *MODES[mode]]

    def start(self, mode: str, run: Path, log: Path) -> subprocess.Popen:
        env = dict(os.environ, WPOT_CAMPAIGN_LOG=str(log),
                   PYTHONPATH=os.pathsep.join([str(self.hook_dir), os.environ.get("PYTHONPATH", "")]))
        return subprocess.Popen(self.command(mode, run), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                env=env, start_new_session=True)  # its own process group: workers die with it

    def finish(self, mode: str, run: Path, log: Path) -> tuple[int, str]:
        p = self.start(mode, run, log)
        _, err = p.communicate(timeout=600)
        return p.returncode, err.decode(errors="replace")


def read_run(run: Path) -> dict:
    """The finished store's matrices and bookkeeping (read with RunStore, as `wpot classify` would)."""
    from wpot.runs.store import RunStore

    with RunStore(run) as s:
        betas, d_beta = s.distance_matrices()
        dup = s.con.execute("SELECT COUNT(*) FROM (SELECT i, j FROM computations GROUP BY i, j HAVING COUNT(*) > 1)").fetchone()[0]
        return {"d": s.distance_matrix(), "betas": betas, "d_beta": d_beta, "n_pairs": len(s.done()),
                "n_tasks": len(s.tasks()), "dup": int(dup), "n_comp": s.n_computations, "failures": len(s.failures())}


def starts(log: Path) -> dict[tuple[int, int], int]:
    """Pair starts per pair from the start log (a line cut by a kill is ignored)."""
    out: dict[tuple[int, int], int] = {}
    if log.is_file():
        for line in log.read_text().splitlines():
            parts = line.split()
            if len(parts) == 2 and all(p.isdigit() for p in parts):
                key = (int(parts[0]), int(parts[1]))
                out[key] = out.get(key, 0) + 1
    return out


def same(a: dict, b: dict) -> bool:
    return (np.array_equal(a["d"], b["d"], equal_nan=True) and np.array_equal(a["betas"], b["betas"])
            and np.array_equal(a["d_beta"], b["d_beta"], equal_nan=True))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kills", type=int, default=50, help="SIGKILLs in all, shared 40/30/30 %% by the modes (default 50)")
    ap.add_argument("--kills-per-trial", type=int, default=5, help="kills on one run folder before it is run to completion")
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", type=Path, default=None, help="working folder (default: a temporary one, removed)")
    a = ap.parse_args(argv)
    rng = random.Random(a.seed)
    tmp = None
    if a.work is None:
        tmp = tempfile.TemporaryDirectory(prefix="wpot-faults-")
        a.work = Path(tmp.name)
    a.work.mkdir(parents=True, exist_ok=True)
    hook = a.work / "hook"
    hook.mkdir(exist_ok=True)
    (hook / "sitecustomize.py").write_text(SITECUSTOMIZE)
    camp = Campaign(a.work, make_dataset(a.work / "data"), hook)
    shares = {m: SHARE[m] for m in a.modes}
    total = sum(shares.values())
    targets = {m: round(a.kills * s / total) for m, s in shares.items()}
    targets[a.modes[0]] += a.kills - sum(targets.values())

    rows, refs, ok_all = [], {}, True
    for mode in a.modes:
        t_mode = time.perf_counter()
        ref_run = a.work / f"ref-{mode.strip('-').replace(' ', '_')}"
        t0 = time.perf_counter()
        rc, err = camp.finish(mode, ref_run, a.work / "ref.log")
        t_ref = time.perf_counter() - t0
        if rc != 0:
            print(f"{mode}: the uninterrupted run failed (exit {rc}):\n{err[-3000:]}", file=sys.stderr)
            return 1
        refs[mode] = ref = read_run(ref_run)
        kills = reruns = trials = dup = recomputed = failures = early = 0
        equal = True
        while kills < targets[mode]:
            trials += 1
            run, log = a.work / f"{ref_run.name}-trial{trials}", a.work / f"{ref_run.name}-trial{trials}.log"
            trial_kills = 0
            while True:
                if trial_kills:
                    reruns += 1
                p = camp.start(mode, run, log)
                delay = rng.uniform(0.0, t_ref)
                try:
                    p.wait(timeout=delay)
                except subprocess.TimeoutExpired:
                    os.killpg(p.pid, signal.SIGKILL)
                    p.wait()
                    kills += 1
                    trial_kills += 1
                    if kills < targets[mode] and trial_kills < a.kills_per_trial:
                        continue
                    reruns += 1
                    rc, err = camp.finish(mode, run, log)  # after the trial's last kill: run to completion
                else:
                    early += 1  # the run finished before its kill moment
                    rc, err = p.returncode, p.stderr.read().decode(errors="replace")
                break
            if rc != 0:
                print(f"{mode} trial {trials}: the final run failed (exit {rc}):\n{err[-3000:]}", file=sys.stderr)
                equal = False
                continue
            got = read_run(run)
            equal &= same(got, ref) and got["n_pairs"] == got["n_tasks"]
            dup += got["dup"]
            failures += got["failures"]
            recomputed += sum(c - 1 for c in starts(log).values())
        rows.append((mode, kills, reruns, trials, "yes" if equal else "NO", dup, recomputed, failures,
                     time.perf_counter() - t_mode))
        ok_all &= equal and dup == 0 and failures == 0

    names = list(refs)
    cross = all(same(refs[names[0]], refs[m]) for m in names[1:])
    print(f"fault campaign: {a.kills} SIGKILLs (whole process group) at random moments, seed {a.seed}; dataset: 6 meshes "
          f"of 60-74 vertices, 15 pairs; {' '.join(SETTINGS)}")
    head = ("mode", "kills", "reruns", "trials", "final D(inf), D(beta) equal", "pairs committed twice",
            "pairs recomputed after a kill", "failures", "time")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]} | {r[3]} | {r[4]} | {r[5]} | {r[6]} | {r[7]} | {r[8]:.0f} s |")
    print(f"uninterrupted runs of the modes equal to each other: {'yes' if cross else 'NO'}")
    if tmp is not None:
        tmp.cleanup()
    return 0 if ok_all and cross else 1


if __name__ == "__main__":
    sys.exit(main())
