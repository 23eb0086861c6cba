"""The non-timing logic of benchmarks/bench_tracker.py: the export of an older tree, the order
of the runs, the rows' settings, medians and comparisons, the cut to the first seconds."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch

from evtrack import Events

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import bench_tracker as bt  # noqa: E402
import revision_trees  # noqa: E402
import tracker_tables  # noqa: E402


def _git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args], cwd=repo,
                          check=True, capture_output=True, text=True).stdout.strip()


@pytest.fixture
def repo(tmp_path: Path) -> Path:
    root = tmp_path / "repo"
    for rel, text in {"evtrack/__init__.py": "X = 1\n", "evtrack/sub/m.py": "Y = 2\n",
                      "models/__init__.py": "M = 3\n", "filters/__init__.py": "F = 4\n",
                      "benchmarks/b.py": "", "README.md": "r\n"}.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)
    _git(root, "init", "-q")
    _git(root, "add", ".")
    _git(root, "commit", "-q", "-m", "first")
    (root / "evtrack/__init__.py").write_text("X = 10\n")
    _git(root, "commit", "-q", "-am", "second")
    return root


def test_export_assembles_the_installed_layout(repo: Path, tmp_path: Path) -> None:
    commit = bt.resolve_revision("HEAD~1", repo / "benchmarks")  # from a subfolder too
    dest = bt.export_package(commit, repo / "benchmarks", tmp_path / "old")
    assert (dest / "evtrack/__init__.py").read_text() == "X = 1\n"  # the revision's, not HEAD's
    assert (dest / "evtrack/sub/m.py").is_file()
    assert (dest / "evtrack/models/__init__.py").read_text() == "M = 3\n"
    assert (dest / "evtrack/filters/__init__.py").read_text() == "F = 4\n"
    assert not (dest / "evtrack/train").exists()  # absent in the revision: left out
    assert not (dest / "models").exists() and not (dest / "benchmarks").exists()
    assert sorted(p.name for p in dest.iterdir()) == sorted([revision_trees.MARKER, "evtrack"])
    out = subprocess.run([sys.executable, "-c", "import evtrack, evtrack.models as m; "
                          "print(evtrack.X, m.M, evtrack.__file__)"], cwd=tmp_path,
                         env={"PYTHONPATH": str(dest), "PATH": "/usr/bin:/bin"},
                         capture_output=True, text=True, check=True).stdout.split()
    assert out[:2] == ["1", "3"] and out[2].startswith(str(dest))


def test_export_is_reused_and_refuses_other_folders(repo: Path, tmp_path: Path) -> None:
    old = bt.resolve_revision("HEAD~1", repo)
    dest = bt.export_package(old, repo, tmp_path / "old")
    (dest / "evtrack/kept.txt").write_text("cache")
    assert bt.export_package(old, repo, dest) == dest
    assert (dest / "evtrack/kept.txt").is_file()  # reused as it was
    with pytest.raises(RuntimeError, match="not empty"):
        bt.export_package(bt.resolve_revision("HEAD", repo), repo, dest)
    other = tmp_path / "other"
    other.mkdir()
    (other / "file").write_text("")
    with pytest.raises(RuntimeError, match="not empty"):
        bt.export_package(old, repo, other)


def test_unknown_revision(repo: Path) -> None:
    with pytest.raises(RuntimeError):
        bt.resolve_revision("no-such-rev", repo)


def test_runs_alternate() -> None:
    orders = [bt.run_order(["old", "new"], i) for i in range(4)]
    assert orders == [["old", "new"], ["new", "old"], ["old", "new"], ["new", "old"]]
    assert bt.run_order(["new"], 1) == ["new"]


def test_config_changes_only_given_options() -> None:
    combo = {"threads": 2, "method": "full", "cap": None, "sample": 0, "budget": None,
             "rt": None, "async": "off", "prior": None}
    changes = bt.config_changes({"flow": {"roi_size": 16}}, combo)
    assert changes == {"flow": {"roi_size": 16}, "method": "full", "torch_threads": 2,
                       "search_per_roi_window": 0, "pose_async": False}
    assert bt.combo_label(combo) == "full sample=0 async=off"


def test_combos_order_threads_first_methods_last() -> None:
    args = bt._parser().parse_args(["--threads", "2", "1", "--methods", "full", "pose"])
    got = [(c["threads"], c["method"]) for c in bt.combos(args)]
    assert got == [(2, "full"), (2, "pose"), (1, "full"), (1, "pose")]


def test_median_row_and_trajectory_comparison() -> None:
    runs = [{"proc_s": t, "rtf": t / 2, "events": 10, "traj": "a"} for t in (3.0, 1.0, 2.0)]
    row = bt.median_row(runs)
    assert row["proc_s"] == 2.0 and row["rtf"] == 1.0 and row["events"] == 10
    assert row["runs"] == [3.0, 1.0, 2.0] and row["trajs"] == ["a"]
    assert tracker_tables.same_trajectory({"trajs": ["a"]}, {"trajs": ["a"]}) == "same"
    assert tracker_tables.same_trajectory({"trajs": ["a"]}, {"trajs": ["b"]}) == "differs"
    assert tracker_tables.same_trajectory({"trajs": ["a", "b"]}, {"trajs": ["a"]}) == "varies"


def test_ratio_summary_and_config_differences() -> None:
    text = bt.ratio_summary([(2.0, 1.0), (1.0, 2.0)])
    assert "geometric mean 1.000 over 2 rows" in text and "min 0.500, max 2.000" in text
    assert "total old 3.00 s, new 3.00 s" in text
    assert bt.config_differences({"a": 1, "b": 2}, {"a": 1, "b": 3, "c": 4}) == [
        "b: 2 -> 3", "c: (absent) -> 4"]


def test_arguments_that_exclude_each_other() -> None:
    ap = bt._parser()
    for argv in (["--oracle", "--weights", "w.pt"], ["--speed", "regular"],
                 ["--export-dir", "d"], ["--repeats", "0"], ["--threads", "0"],
                 ["--duration", "0"], ["--benchmark", "b", "--save-sequence", "s"]):
        with pytest.raises(SystemExit):
            bt.check_arguments(ap, ap.parse_args(argv))
    with pytest.raises(SystemExit):
        ap.parse_args(["--sequence", "a", "--benchmark", "b"])
    bt.check_arguments(ap, ap.parse_args(["--benchmark", "b", "--speed", "all", "--baseline",
                                          "HEAD", "--export-dir", "d", "--oracle"]))


class _Stream:
    """What truncate uses of a Sequence: the frame times and the event stream."""

    def __init__(self, t: list[int]) -> None:
        n = len(t)
        self.events = Events(torch.zeros(n, dtype=torch.int32), torch.zeros(n, dtype=torch.int32),
                             torch.tensor(t), torch.ones(n, dtype=torch.int8))
        self.rgb_times_us = torch.tensor([0, 400_000, 800_000])
        self.depth_times_us = torch.tensor([100_000, 600_000])

    def iter_events(self, window_us=None, count=None):
        if count is not None:
            yield from (self.events[i:i + count] for i in range(0, len(self.events), count))
        else:
            yield from self.events.windows(duration_us=window_us)


def test_truncate_keeps_the_first_seconds() -> None:
    seq = _Stream([50_000 + 10_000 * i for i in range(100)])  # 50 ms .. 1.04 s
    bt.truncate(seq, 0.5)  # up to 550 ms
    assert seq.rgb_times_us.tolist() == [0, 400_000]
    assert seq.depth_times_us.tolist() == [100_000]
    chunks = list(seq.iter_events(window_us=120_000))
    t = torch.cat([c.t for c in chunks])
    assert t.tolist() == [50_000 + 10_000 * i for i in range(50)]
    assert int(t.max()) < 550_000
