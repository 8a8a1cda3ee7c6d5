"""Mutation fuzzing of the file readers through the ``slam`` command line, shared by the suite's hypothesis
tests (``tests/test_fuzz_readers.py``, a few dozen cases per format) and the campaign outside CI
(``benchmarks/fuzz_campaign.py``, thousands).

A case takes a small valid seed file of one format (CARMEN, g2o, TORO, TUM, KITTI, relations, MCAP, ROS 1
bag, the SQLite file of a ROS 2 bag, read in its folder), damages it (bytes flipped, zeroed or inserted, the file cut), runs the command that reads it whole
in this process, and classifies the outcome. Allowed: ``ok`` (exit 0, and what it reports agrees with an
independent count of the damaged file: no silently different graph size or scan count) and ``error``
(exit 2 with exactly one ``error:`` line). Anything else is a finding: ``traceback`` (an exception
escaped), ``bad`` (another exit status, or not one line), ``hang`` (no answer within the time limit) or
``mismatch`` (exit 0 with counts the damaged file does not hold).
"""

from __future__ import annotations

import contextlib
import io
import json
import re
import signal
import tempfile
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

FORMATS = ("carmen", "g2o", "toro", "tum", "kitti", "relations", "mcap", "bag", "ros2")
MUTATIONS = ("flip", "bit", "zero", "insert", "delete", "truncate")
ALLOWED = ("ok", "error")


@dataclass
class Seed:
    """A valid file of one format, the command that reads it, and the count its output must agree with."""

    fmt: str
    suffix: str
    data: bytes
    args: Callable[[Path], list[str]]  # the command line for a file
    oracle: Callable[[bytes, str], str | None]  # (damaged bytes, stdout of a success) → why it disagrees, or None


@dataclass
class Outcome:
    kind: str  # ok, error, traceback, bad, hang, mismatch
    detail: str = ""


class _Hang(BaseException):
    """Raised by the alarm: not an Exception, so no handler of the command swallows it."""


def mutate(data: bytes, kind: str, where: float, payload: bytes) -> bytes:
    """*data* damaged at the fraction *where* of its length: *payload* XOR-ed in (``flip``), one bit of the byte
    there flipped (``bit``, chosen by the payload's first byte: a digit often stays a digit), zeroed over the
    payload's length (``zero``), the payload inserted (``insert``), as many bytes deleted (``delete``), or the
    file cut there (``truncate``)."""
    i = min(int(where * len(data)), max(len(data) - 1, 0))
    if kind == "truncate":
        return data[:i]
    if kind == "insert":
        return data[:i] + payload + data[i:]
    if kind == "delete":
        return data[:i] + data[i + len(payload):]
    b = bytearray(data)
    if kind == "bit":
        if b:
            b[i] ^= 1 << (payload[0] % 8)
        return bytes(b)
    for k, p in enumerate(payload[: len(b) - i]):
        b[i + k] = 0 if kind == "zero" else b[i + k] ^ (p or 0xFF)
    return bytes(b)


# ----------------------------------------------------------------------------- independent counts

def _records(data: bytes) -> list[list[bytes]]:
    """The token lists of the non-blank, non-comment lines (split as a C reader would: ASCII white space)."""
    out = []
    for line in data.split(b"\n"):
        tok = line.split()
        if tok and not tok[0].startswith(b"#"):
            out.append(tok)
    return out


def _field(stdout: str, key: str) -> str | None:
    m = re.search(rf"^{re.escape(key)}: (.*)$", stdout, re.M)
    return m.group(1).strip() if m else None


def _carmen_oracle(data: bytes, stdout: str) -> str | None:
    topic, scans = _field(stdout, "sensor_topic"), _field(stdout, "scans")
    want = sum(1 for t in _records(data) if t[0].decode("latin-1") == topic)
    return None if scans == str(want) else f"scans {scans}, the file has {want} {topic} lines"


def _graph_oracle(data: bytes, stdout: str) -> str | None:
    rec = json.loads(stdout)
    recs = _records(data)
    edges = [t for t in recs if t[0].startswith(b"EDGE")]
    vertices = [t for t in recs if t[0].startswith(b"VERTEX")]
    ids = {t[1] for t in vertices} if vertices else {v for t in edges if not t[0].endswith(b"PRIOR_SE2")
                                                    and not t[0].endswith(b"SE3_PRIOR") for v in t[1:3]}
    if (rec["nodes"], rec["edges"]) != (len(ids), len(edges)):
        return f"solved {rec['nodes']} nodes / {rec['edges']} edges, the file has {len(ids)} / {len(edges)}"
    return None


def _pairs_oracle(data: bytes, stdout: str) -> str | None:
    pairs, lines = _field(stdout, "pairs"), len(_records(data))
    return None if pairs == str(lines) else f"pairs {pairs}, the file has {lines} pose lines"


def _pairs_at_most_oracle(data: bytes, stdout: str) -> str | None:
    """TUM stamps may coincide within the association tolerance: at most one pair per line."""
    pairs, lines = int(_field(stdout, "pairs") or -1), len(_records(data))
    return None if 1 <= pairs <= lines else f"pairs {pairs}, the file has {lines} pose lines"


def _relations_oracle(data: bytes, stdout: str) -> str | None:
    used, missing = int(_field(stdout, "n_used") or -1), int(_field(stdout, "n_missing") or -1)
    lines = len(_records(data))
    return None if used + missing == lines else f"{used} used + {missing} missing, the file has {lines} lines"


def _mcap_oracle(data: bytes, stdout: str) -> str | None:
    """Only where the mcap library itself reads the damaged file whole: the same number of sensor messages."""
    from mcap.reader import make_reader

    topic, scans = _field(stdout, "sensor_topic"), _field(stdout, "scans")
    try:
        n = sum(1 for _, ch, _ in make_reader(io.BytesIO(data)).iter_messages() if ch.topic == topic)
    except Exception:  # noqa: BLE001 - the library cannot tell: no independent count
        return None
    return None if scans == str(n) else f"scans {scans}, the mcap library reads {n} {topic} messages"


def _rosbags_count(stdout: str, open_reader: Callable[[], object]) -> str | None:
    """Only where rosbags reads the damaged container whole: the same number of sensor messages as reported."""
    topic, scans = _field(stdout, "sensor_topic"), _field(stdout, "scans")
    try:
        with open_reader() as r:  # type: ignore[attr-defined]
            n = sum(1 for c, _, _ in r.messages() if c.topic == topic)
    except Exception:  # noqa: BLE001 - the library cannot tell: no independent count
        return None
    return None if scans == str(n) else f"scans {scans}, rosbags reads {n} {topic} messages"


def _bag_oracle(data: bytes, stdout: str) -> str | None:
    from rosbags.rosbag1 import Reader

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "b.bag"
        p.write_bytes(data)
        return _rosbags_count(stdout, lambda: Reader(p))


def _ros2_oracle(data: bytes, stdout: str) -> str | None:
    from rosbags.rosbag2 import Reader

    return _rosbags_count(stdout, lambda: Reader(Path(_field(stdout, "file") or "")))


def _in_bag_folder(metadata: bytes, db3_name: str) -> Callable[[Path], list[str]]:
    """The command for a (damaged) SQLite file: ``slam info`` on a fresh bag folder holding it under its own name
    beside the seed bag's metadata.yaml."""
    def args(p: Path) -> list[str]:
        folder = p.parent / "case_bag"
        folder.mkdir(exist_ok=True)
        for old in folder.iterdir():
            old.unlink()
        (folder / "metadata.yaml").write_bytes(metadata)
        (folder / db3_name).write_bytes(p.read_bytes())
        return ["info", str(folder)]
    return args


# ----------------------------------------------------------------------------- seeds

def _tum_text(n: int, rng: np.random.Generator) -> str:
    t = (100.0 + 0.1 * np.arange(n)).tolist()
    xy = np.cumsum(rng.normal(0, 0.1, (n, 2)), axis=0).tolist()
    th = np.cumsum(rng.normal(0, 0.05, n))
    s, c = np.sin(th / 2).tolist(), np.cos(th / 2).tolist()
    return "".join(f"{t[k]!r} {xy[k][0]!r} {xy[k][1]!r} 0.0 0.0 0.0 {s[k]!r} {c[k]!r}\n" for k in range(n))


def seeds(workdir: Path) -> dict[str, list[Seed]]:
    """The seed files of every format (deterministic; MCAP and bags in each chunk compression), some written
    into *workdir* as fixed companions."""
    from core import geometry as geo
    from core import pose_formats
    from slam.graph import PoseGraph, write_g2o, write_toro
    from tests.test_logs_carmen import synthetic_log
    from tests.test_logs_mcap import write_basic_log
    from tests.test_logs_rosbag1 import write_bag
    from tests.test_logs_rosbag2 import write_rosbag2

    rng = np.random.default_rng(27)
    out: dict[str, list[Seed]] = {}
    carmen = ("\n".join(synthetic_log(rng, n_scans=12, n_beams=30)) + "\n").encode()
    out["carmen"] = [Seed("carmen", ".clf", carmen, lambda p: ["info", str(p)], _carmen_oracle)]

    g = PoseGraph(2)
    P = geo.xytheta_to_matrix(np.cumsum(rng.normal(0, 1, (15, 3)), axis=0))
    for k in range(15):
        g.add_node(k, P[k])
    info = np.diag([50.0, 50.0, 200.0])
    for i, j in [(k, k + 1) for k in range(14)] + [(0, 7), (3, 12), (5, 14)]:
        g.add_edge(i, j, geo.relative(P[i], P[j]) @ geo.xytheta_to_matrix(*rng.normal(0, 0.02, 3)), info)
    for fmt, write, suffix in (("g2o", write_g2o, ".g2o"), ("toro", write_toro, ".graph")):
        write(g, workdir / f"seed{suffix}")
        out[fmt] = [Seed(fmt, suffix, (workdir / f"seed{suffix}").read_bytes(),
                         lambda p: ["solve", str(p), "--backend", "chordal", "--init", "odometry"], _graph_oracle)]

    tum = _tum_text(25, rng)
    out["tum"] = [Seed("tum", ".tum", tum.encode(), lambda p: ["eval", "ape", str(p), str(p)], _pairs_at_most_oracle)]
    T = pose_formats.pose_from_quat(np.zeros((25, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (25, 1)))
    T[:, :3, 3] = rng.normal(0, 3, (25, 3))
    kitti = "".join(" ".join(repr(float(v)) for v in M[:3].ravel()) + "\n" for M in T)
    out["kitti"] = [Seed("kitti", ".kitti", kitti.encode(), lambda p: ["eval", "ape", str(p), str(p), "--est-format",
                                                                      "kitti", "--ref-format", "kitti"], _pairs_oracle)]
    (workdir / "traj.tum").write_text(tum)
    st = [float(line.split()[0]) for line in tum.splitlines()]
    rel = "".join(f"{st[k]!r} {st[k + 3]!r} 0.3 -0.1 0.0 0.0 0.0 0.05\n" for k in range(0, 20, 2))
    traj = workdir / "traj.tum"
    out["relations"] = [Seed("relations", ".relations", rel.encode(),
                             lambda p: ["eval", "relations", str(traj), str(p)], _relations_oracle)]

    out["mcap"], out["bag"], out["ros2"] = [], [], []
    for comp in ("zstd", "lz4", "none"):
        p = workdir / f"seed_{comp}.mcap"
        write_basic_log(p, n=15, chunk_size=4096, compression=comp)
        out["mcap"].append(Seed("mcap", ".mcap", p.read_bytes(), lambda p: ["info", str(p)], _mcap_oracle))
    write_rosbag2(workdir / "seed_none.mcap", workdir / "seed_ros2")
    db3 = next((workdir / "seed_ros2").glob("*.db3"))
    out["ros2"].append(Seed("ros2", ".db3", db3.read_bytes(),
                            _in_bag_folder((workdir / "seed_ros2" / "metadata.yaml").read_bytes(), db3.name), _ros2_oracle))
    for comp in ("bz2", "lz4", None):
        p = workdir / f"seed_{comp or 'none'}.bag"
        write_bag(p, n=15, compression=comp, chunk_threshold=6000)
        out["bag"].append(Seed("bag", ".bag", p.read_bytes(), lambda p: ["info", str(p)], _bag_oracle))
    return out


# ----------------------------------------------------------------------------- one case

def run_case(seed: Seed, data: bytes, workdir: Path, timeout_s: int = 30) -> Outcome:
    """Write *data* as a file of *seed*'s format, run its command in this process, classify the outcome."""
    from slam.cli import main

    path = workdir / f"case{seed.suffix}"
    path.write_bytes(data)
    out, err = io.StringIO(), io.StringIO()

    def alarm(signum, frame):  # type: ignore[no-untyped-def]
        raise _Hang

    previous = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(timeout_s)
    code: object = 0
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            main(seed.args(path))
    except SystemExit as exc:
        code = exc.code or 0
    except _Hang:
        return Outcome("hang", f"no answer within {timeout_s} s")
    except Exception:  # noqa: BLE001 - this is what the campaign looks for
        return Outcome("traceback", traceback.format_exc(limit=-3))
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    lines = err.getvalue().strip().splitlines()
    if code == 2 and len(lines) == 1 and lines[0].startswith("error: "):
        return Outcome("error", lines[0])
    if code != 0:
        return Outcome("bad", f"exit {code}: {err.getvalue()[-500:]}")
    why = seed.oracle(data, out.getvalue())
    return Outcome("mismatch", why) if why else Outcome("ok")
