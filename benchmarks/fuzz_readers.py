"""Fuzz wpot's file readers: OFF, PLY (ASCII and binary), OBJ, STL (ASCII and binary), .mat (TOSCA and SHREC'19
layouts), .vts landmarks and vertex maps.

The contract (issue 22): on any input a reader returns or raises `ValueError` / `OSError`; it never raises
anything else, never crashes the interpreter, never hangs, and never reads past the end of the file (every
reader reads the file's bytes once with `Path.read_bytes` and parses that buffer, so the file level is safe by
construction; a parser indexing past its buffer shows up here as an exception other than ValueError, which
`wpot.io` turns into a ValueError naming the file, or as a crash).

Inputs are generated from valid seed files written by `wpot.save_mesh` / `save_vts` / `save_vertex_map` (and
a binary PLY, an ASCII STL and a SHREC'19 .mat built here), by

* mutation: truncation, byte flips, inserted / deleted / duplicated chunks, splices of two seeds, numbers
  replaced by extreme tokens (huge counts, negative, NaN, inf, 1e308, fractions);
* structure: headers declaring huge element counts (OFF, PLY, binary STL), faces with odd arities and
  indices, .mat files with odd field shapes, dtypes (complex, bool, text, cells) and layouts;
* random bytes.

Each input runs under a 10 s alarm in one of ``--workers`` processes, each with a 4 GiB address-space limit
(a reader that tries to allocate for a header's claim fails with MemoryError instead of taking the machine);
the parent sees a worker that dies (a crash) or stalls past the alarm (a hang). A ValueError whose message
shows a MemoryError is counted apart: a "memory bomb", allowed by the contract but worth knowing.

Usage::

    python benchmarks/fuzz_readers.py                    # 100,000 inputs, 2 worker processes
    python benchmarks/fuzz_readers.py -n 2000 --seed 3

Prints per format: inputs, accepted, ValueError, OSError, memory bombs, other exceptions, crashes, hangs,
the slowest input's time; and the first offending inputs, saved under ``--keep`` (default: a temporary folder).
`tests/test_reliability.py` runs a few hundred of the same inputs (`generate`) in the suite.
"""
from __future__ import annotations

import argparse
import io
import os
import random
import signal
import struct
import sys
import tempfile
import time
import traceback
import warnings
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

FORMATS = [".off", ".ply", ".bply", ".obj", ".stl", ".bstl", ".mat", ".smat", ".vts", ".map"]
EXTREME = [b"0", b"-1", b"1", b"3", b"4", b"-0", b"nan", b"inf", b"-inf", b"1e308", b"-1e308", b"9999999999",
           b"99999999999999999999999", b"2147483648", b"0.5", b"1e-320", b"", b"x", b"0x10", b"3 3 3 3"]
HALT = 10  # seconds per input before it counts as a hang


def seed_files() -> dict[str, bytes]:
    """Valid files of every format, on a small mesh (50 vertices)."""
    import scipy.io

    from wpot.examples import example_mesh
    from wpot.io import save_mesh, save_vertex_map, save_vts

    m = example_mesh(50, seed=1)
    out: dict[str, bytes] = {}
    with tempfile.TemporaryDirectory() as d:
        for ext in (".off", ".ply", ".obj", ".mat"):
            out[ext] = save_mesh(m, Path(d) / f"s{ext}").read_bytes()
        out[".vts"] = save_vts(np.arange(0, 40, 3), Path(d) / "s.vts").read_bytes()
        out[".map"] = save_vertex_map(np.arange(50)[::-1], Path(d) / "s.txt").read_bytes()
    v, f = m.vertices, m.faces
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(v)}\nproperty float x\nproperty float y\n"
            f"property float z\nelement face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    body = v.astype("<f4").tobytes() + b"".join(struct.pack("<B3i", 3, *map(int, t)) for t in f)
    out[".bply"] = head + body
    out[".bstl"], out[".stl"] = _binary_stl(v, f), _ascii_stl(v, f)
    buf = io.BytesIO()
    scipy.io.savemat(buf, {"shape": {"VERT": v, "TRIV": (f + 1).astype(np.float64)}})
    out[".smat"] = buf.getvalue()
    return out


def _binary_stl(v: np.ndarray, f: np.ndarray) -> bytes:
    rec = b"".join(struct.pack("<12fH", 0, 0, 0, *v[t[0]], *v[t[1]], *v[t[2]], 0) for t in f)
    return b"\0" * 80 + struct.pack("<I", len(f)) + rec


def _ascii_stl(v: np.ndarray, f: np.ndarray) -> bytes:
    lines = ["solid s"]
    for t in f:
        lines += ["facet normal 0 0 0", "outer loop", *(f"vertex {x:.17g} {y:.17g} {z:.17g}" for x, y, z in v[t]), "endloop", "endfacet"]
    return ("\n".join(lines + ["endsolid s"]) + "\n").encode()


# ------------------------------------------------------------------------------------------ generators
def _mutate(rng: random.Random, data: bytes, other: bytes) -> bytes:
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        op = rng.randrange(8)
        n = len(b)
        at = rng.randrange(n + 1) if n else 0
        if op == 0 and n:  # truncate
            del b[at:]
        elif op == 1 and n:  # flip bytes
            for _ in range(rng.randint(1, 8)):
                b[rng.randrange(len(b))] = rng.randrange(256)
        elif op == 2:  # insert random bytes
            b[at:at] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 16)))
        elif op == 3 and n:  # delete a chunk
            del b[at:at + rng.randint(1, 64)]
        elif op == 4 and n:  # duplicate a chunk
            k = rng.randint(1, 200)
            b[at:at] = b[at:at + k] * rng.randint(1, 4)
        elif op == 5:  # splice another seed
            cut = rng.randrange(len(other) + 1)
            b = b[:at] + bytearray(other[cut:])
        elif op == 6 and n:  # replace a number token by an extreme one
            text = bytes(b).split(b" ")
            if len(text) > 1:
                k = rng.randrange(len(text))
                tail = b"\n" if text[k].endswith(b"\n") else b""
                text[k] = rng.choice(EXTREME) + tail
                b = bytearray(b" ".join(text))
        elif op == 7 and n:  # replace a whole line
            lines = bytes(b).split(b"\n")
            lines[rng.randrange(len(lines))] = b" ".join(rng.choice(EXTREME) for _ in range(rng.randint(0, 5)))
            b = bytearray(b"\n".join(lines))
    return bytes(b)


def _structured(rng: random.Random, fmt: str) -> bytes:
    """A file whose structure is right but whose numbers are not (huge counts, odd arities, odd arrays)."""
    big = rng.choice([0, 1, 3, 2**31 - 1, 2**31, 2**40, 10**12, -1, 7])
    if fmt == ".off":
        nv, nf = rng.choice([big, 3, 4]), rng.choice([big, 1, 2])
        verts = "\n".join(" ".join(rng.choice(["0", "1", "nan", "1e308", "-inf", "0.5", "x"]) for _ in range(rng.randint(2, 4)))
                          for _ in range(rng.randint(0, 5)))
        faces = "\n".join(" ".join(str(rng.choice([3, 4, 0, -1, 2, big, 1])) for _ in range(rng.randint(1, 6)))
                          for _ in range(rng.randint(0, 4)))
        return f"OFF\n{nv} {nf} 0\n{verts}\n{faces}\n".encode()
    if fmt in (".ply", ".bply"):
        binary = fmt == ".bply" or rng.random() < 0.3
        t = rng.choice(["float", "double", "uchar", "int", "short", "char", "uint", "bogus"])
        lt = rng.choice(["uchar", "int", "uint", "float", "bogus"])
        head = (f"ply\nformat {'binary_little_endian' if binary else 'ascii'} 1.0\nelement vertex {big}\n"
                f"property {t} x\nproperty {t} y\nproperty {t} z\nelement face {rng.choice([big, 1, 2])}\n"
                f"property list {lt} int vertex_indices\nend_header\n").encode()
        body = bytes(rng.randrange(256) for _ in range(rng.randint(0, 300))) if binary else \
            "\n".join(" ".join(str(rng.choice([0, 1, 3, 4, -1, big, 2.5])) for _ in range(rng.randint(1, 5)))
                      for _ in range(rng.randint(0, 8))).encode()
        return head + body
    if fmt == ".obj":
        lines = []
        for _ in range(rng.randint(0, 12)):
            kind = rng.choice(["v", "f", "vt", "vn", "o", "g", "usemtl", "l", "s"])
            nums = [str(rng.choice([0, 1, 2, 3, -1, -2, -4, big, 0.5, "1/1/1", "2//2", "nan", "1e308", "/"]))
                    for _ in range(rng.randint(0, 6))]
            lines.append(" ".join([kind, *nums]))
        return ("\n".join(lines) + "\n").encode()
    if fmt in (".stl", ".bstl"):
        if fmt == ".bstl":
            n = rng.choice([big & 0xFFFFFFFF, 0, 1, 2])
            return b"\0" * 80 + struct.pack("<I", n) + bytes(rng.randrange(256) for _ in range(rng.choice([0, 50, 100, 150])))
        facets = []
        for _ in range(rng.randint(0, 4)):
            vs = [f"vertex {' '.join(rng.choice(['0', '1', 'nan', '1e308', 'x', '-0']) for _ in range(rng.randint(2, 4)))}"
                  for _ in range(rng.randint(0, 4))]
            facets.append("facet normal 0 0 1\nouter loop\n" + "\n".join(vs) + "\nendloop\nendfacet")
        return ("solid x\n" + "\n".join(facets) + "\nendsolid x\n").encode()
    if fmt in (".mat", ".smat"):
        import scipy.io

        def arr() -> object:
            shape = tuple(rng.choice([0, 1, 2, 3, 5]) for _ in range(rng.randint(0, 3)))
            kind = rng.choice(["f", "i", "c", "b", "s", "cell", "nan", "neg"])
            if kind == "s":
                return "text"
            if kind == "cell":
                return np.array([np.zeros(2), "x"], dtype=object)
            a = np.ones(shape)
            if kind == "i":
                return a.astype(np.int32) * rng.choice([1, 0, -1, 7, 2**30])
            if kind == "c":
                return a + 1j
            if kind == "b":
                return a.astype(bool)
            if kind == "nan":
                return a * np.nan
            if kind == "neg":
                return -a
            return a * rng.choice([1.0, 0.5, 1e308, 3.0])
        layout = ("X", "Y", "Z", "TRIV") if fmt == ".mat" else ("VERT", "TRIV")
        fields = {k: arr() for k in layout if rng.random() < 0.9}
        d = {"surface": fields} if rng.random() < 0.7 else fields
        if rng.random() < 0.2:
            d["other"] = dict(fields)
        buf = io.BytesIO()
        try:
            scipy.io.savemat(buf, d or {"empty": np.zeros(0)}, do_compression=rng.random() < 0.5)
        except Exception:  # savemat refuses some of these layouts: use random bytes with a .mat header
            return b"MATLAB 5.0 MAT-file" + bytes(rng.randrange(256) for _ in range(200))
        return buf.getvalue()
    lines = [rng.choice(["1", "0", "-1", "50", "51", "1.0", "1.5", "nan", "1e19", "99999999999999999999", "",
                         "1 2", "x", "\xe9", "\x00"]) for _ in range(rng.randint(0, 10))]
    return "\n".join(lines).encode("utf-8", errors="replace")


def generate(n: int, seed: int = 0, formats: list[str] | None = None) -> Iterator[tuple[str, bytes]]:
    """``n`` fuzz inputs as (format, bytes), deterministic for a seed: 70 % mutated seeds, 20 % structured,
    10 % random bytes, formats in turn."""
    rng = random.Random(seed)
    seeds = seed_files()
    formats = formats or FORMATS
    for k in range(n):
        fmt = formats[k % len(formats)]
        r = rng.random()
        if r < 0.7:
            data = _mutate(rng, seeds[fmt], seeds[rng.choice(FORMATS)])
        elif r < 0.9:
            data = _structured(rng, fmt)
        else:
            data = bytes(rng.randrange(256) for _ in range(rng.randint(0, 512)))
        yield fmt, data


def reader(fmt: str) -> tuple[str, Callable[[Path], object]]:
    """The file extension and reader for a fuzz format."""
    from wpot.io import load_mesh, load_vertex_map, load_vts

    if fmt in (".vts",):
        return ".vts", load_vts
    if fmt == ".map":
        return ".txt", lambda p: load_vertex_map(p, n_vertices=50)
    return {".bply": ".ply", ".bstl": ".stl", ".smat": ".mat"}.get(fmt, fmt), load_mesh


def run_one(fmt: str, data: bytes, folder: Path) -> tuple[str, str]:
    """Read one input: ("ok" | "ValueError" | "OSError" | "memory" | "other", message)."""
    ext, fn = reader(fmt)
    p = folder / f"input{ext}"
    p.write_bytes(data)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            fn(p)
            return "ok", ""
        except ValueError as exc:
            return ("memory" if "MemoryError" in str(exc) else "ValueError"), str(exc)[:300]
        except OSError as exc:
            return "OSError", str(exc)[:300]
        except Exception as exc:  # noqa: BLE001 - the finding
            return "other", f"{type(exc).__name__}: {exc}\n{traceback.format_exc()[-1500:]}"


def _worker(job: tuple[int, int, int, list[str] | None], skip: frozenset = frozenset(), last: str = "") -> dict:
    """Run inputs [start, stop) of the stream (seeded by ``seed``), except those in ``skip``, and return the counts
    and offenders. Before each input its index goes to the file ``last``, so a crash can be traced to it."""
    import resource

    start, stop, seed, formats = job
    resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))

    def alarm(signum, frame):
        raise TimeoutError("hang")

    signal.signal(signal.SIGALRM, alarm)
    counts: dict[str, dict[str, int]] = {}
    slow: dict[str, float] = {}
    bad: list[tuple[str, str, bytes]] = []
    with tempfile.TemporaryDirectory(dir="/dev/shm" if os.path.isdir("/dev/shm") else None) as d:
        for k, (fmt, data) in enumerate(generate(stop, seed, formats)):
            if k < start or k in skip:
                continue
            if last:
                Path(last).write_text(str(k))
            t0 = time.perf_counter()
            signal.alarm(HALT)
            try:
                kind, msg = run_one(fmt, data, Path(d))
            except TimeoutError:
                kind, msg = "hang", f"still running after {HALT} s"
            except MemoryError as exc:
                kind, msg = "other", f"MemoryError: {exc}"
            finally:
                signal.alarm(0)
            dt = time.perf_counter() - t0
            slow[fmt] = max(slow.get(fmt, 0.0), dt)
            counts.setdefault(fmt, {})
            counts[fmt][kind] = counts[fmt].get(kind, 0) + 1
            if kind in ("other", "hang", "memory") and len(bad) < 20:
                bad.append((fmt, f"{kind}: {msg}", data))
    return {"counts": counts, "slow": slow, "bad": bad}


def _crashed_here(n: int, last: Path, skips: dict[int, set[int]]) -> bool:
    """Whether chunk ``n`` died on the input its ``last`` file names (then skipped from now on). A chunk that
    was only collateral damage of another's crash (the whole pool breaks) names an input it had not finished
    either; it is counted once: the index goes to ``skips`` only if that chunk dies there again."""
    text = last.read_text().strip()
    if not text.isdigit():  # killed while writing it: collateral damage
        return False
    k = int(text)
    seen = getattr(_crashed_here, "seen", set())
    _crashed_here.seen = seen
    if (n, k) in seen:
        skips[n].add(k)
        return True
    seen.add((n, k))
    return False


def main(argv: list[str] | None = None) -> int:
    import concurrent.futures as cf
    import multiprocessing as mp

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-n", type=int, default=100_000, help="inputs in all (default 100,000)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--chunk", type=int, default=2000, help="inputs per worker task")
    ap.add_argument("--keep", type=Path, default=None, help="folder for offending inputs")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    jobs = [(s, min(s + a.chunk, a.n), a.seed + s, None) for s in range(0, a.n, a.chunk)]
    # each chunk is its own stream (seed + start) so that no worker regenerates the inputs before its chunk
    jobs = [(0, stop - start, seed, f) for start, stop, seed, f in jobs]
    counts: dict[str, dict[str, int]] = {}
    slow: dict[str, float] = {}
    bad: list[tuple[str, str, bytes]] = []
    crashes = 0
    lastdir = Path(tempfile.mkdtemp(prefix="wpot-fuzz-last-"))
    skips: dict[int, set[int]] = {n: set() for n in range(len(jobs))}
    remaining = set(range(len(jobs)))
    while remaining:  # a crash breaks the pool: the input is recorded, skipped, and its chunk rerun in a new pool
        for f in lastdir.iterdir():
            f.unlink()
        with cf.ProcessPoolExecutor(a.workers, mp_context=mp.get_context("spawn")) as ex:
            futs = {ex.submit(_worker, jobs[n], frozenset(skips[n]), str(lastdir / f"{n}")): n for n in sorted(remaining)}
            for fut in cf.as_completed(futs):
                n = futs[fut]
                try:
                    r = fut.result()
                except cf.process.BrokenProcessPool:
                    lf = lastdir / f"{n}"
                    if lf.is_file() and fut.exception() is not None and _crashed_here(n, lf, skips):
                        crashes += 1
                        k = int(lf.read_text())
                        fmt, data = list(generate(k + 1, jobs[n][2], jobs[n][3]))[k]
                        counts.setdefault(fmt, {})["crash"] = counts.setdefault(fmt, {}).get("crash", 0) + 1
                        bad.append((fmt, f"crash: the reader killed its process (input {k} of chunk {n})", data))
                    continue
                remaining.discard(n)
                for fmt, c in r["counts"].items():
                    for k, v in c.items():
                        counts.setdefault(fmt, {})[k] = counts.setdefault(fmt, {}).get(k, 0) + v
                for fmt, sl in r["slow"].items():
                    slow[fmt] = max(slow.get(fmt, 0.0), sl)
                bad += r["bad"]
    keep = a.keep or Path(tempfile.mkdtemp(prefix="wpot-fuzz-"))
    total = sum(sum(c.values()) for c in counts.values())
    print(f"fuzzed wpot's readers with {total:,} generated inputs (seed {a.seed}) in {time.perf_counter() - t0:.0f} s; "
          f"worker crashes: {crashes}")
    cols = ["ok", "ValueError", "OSError", "memory", "other", "hang", "crash"]
    print("| format | inputs | accepted | ValueError | OSError | memory bombs | other exceptions | hangs | crashes | slowest |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for fmt in FORMATS:
        c = counts.get(fmt, {})
        print(f"| {fmt} | {sum(c.values()):,} | " + " | ".join(f"{c.get(k, 0):,}" for k in cols) + f" | {slow.get(fmt, 0):.2f} s |")
    for n, (fmt, what, data) in enumerate(bad[:20]):
        path = keep / f"bad{n}{reader(fmt)[0] if fmt != '?' else '.bin'}"
        keep.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
        print(f"  {fmt}: {what.splitlines()[0] if what else ''} -> {path}")
    return 0 if not bad else 1


if __name__ == "__main__":
    sys.exit(main())
