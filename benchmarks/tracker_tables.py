"""The tables of ``benchmarks/bench_tracker.py``: its rows (dicts of timings and errors) printed
one per line, and the comparison of two trees' trajectories."""

from __future__ import annotations

__all__ = ["print_compact", "print_wide", "same_trajectory"]


def same_trajectory(old: dict, new: dict) -> str:
    """``same`` (one trajectory in each tree, identical), ``differs``, or ``varies`` (a tree's
    repeated runs did not all give the same trajectory)."""
    if len(old["trajs"]) == 1 and old["trajs"] == new["trajs"]:
        return "same"
    if len(old["trajs"]) > 1 or len(new["trajs"]) > 1:
        return "varies"
    return "differs"


def print_wide(rows: list[dict]) -> None:
    """One line per row with every option and timing (one tree, one sequence)."""
    head = (f"{'method':<10} {'thr':>3} {'async':>5} {'prior':>5} {'cap':>6} {'sample':>6} "
            f"{'budget':>6} "
            f"{'rt':>4} {'min bgt':>7} {'min ev':>6} "
            f"{'unsearched':>10} {'thinned':>8} "
            f"{'proc s':>7} "
            f"{'rtf':>6} {'pose src':>8} "
            f"{'ev/s':>9} {'flow':>6} "
            f"{'veloc':>6} {'pose':>6} {'frames':>6} {'grp p50':>8} {'grp p95':>8} "
            f"{'filt/step':>9}  error")
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r['method']:<10} {r['threads']:>3} {r['async']:>5} {r['prior']:>5} {r['cap']:>6} "
              f"{r['sample']:>6} {r['budget']:>6} {r['rt']:>4g} {r['budget_min']:>7} "
              f"{r['events_min']:>6} "
              f"{r['unsearched']:>10} "
              f"{r['thinned']:>8} {r['proc_s']:>7.2f} {r['rtf']:>6.2f} "
              f"{r['pose_src']:>8.2f} "
              f"{r['ev_per_s']:>9.0f} {r['flow']:>6.2f} {r['velocity']:>6.2f} {r['pose']:>6.2f} "
              f"{r['frames']:>6.2f} {r['group_p50_ms']:>6.2f}ms {r['group_p95_ms']:>6.2f}ms "
              f"{r['step_us']:>7.0f}us  {r.get('error', '')}"
              + (f"  runs {' '.join(f'{t:.2f}' for t in r['runs'])}" if len(r['runs']) > 1
                 else ""))


def print_compact(table: list[tuple[str, dict, dict]], baseline: bool) -> None:
    """One line per row and tree: ``table`` is (label, {code: row}, combo) per sequence and
    setting; with ``baseline`` the new/old time ratio and whether the trajectories agree."""
    width = max([len(label) for label, _, _ in table] + [8])
    seq_w = max([len(rows[next(iter(rows))]["sequence"]) for _, rows, _ in table] + [8])
    head = (f"{'sequence':<{seq_w}} {'run':<{width}} {'thr':>3} "
            + (f"{'code':<4} " if baseline else "")
            + f"{'proc s':>7} {'rtf':>6} {'ev/s':>9} {'flow':>6} {'veloc':>6} {'pose':>6} "
            f"{'frames':>6} {'pose src':>8} {'grp p50':>8} {'grp p95':>8} "
            + (f"{'new/old':>7} {'traj':>7} " if baseline else "")
            + f"{'error':<20} runs (s)")
    print(head)
    print("-" * len(head))
    for label, rows, _ in table:
        for code, r in rows.items():
            extra = ""
            if baseline:
                if code == "new" and "old" in rows:
                    extra = (f"{r['proc_s'] / rows['old']['proc_s']:>7.3f} "
                             f"{same_trajectory(rows['old'], r):>7} ")
                else:
                    extra = f"{'':>7} {'':>7} "
            print(f"{r['sequence']:<{seq_w}} {label:<{width}} {r['threads']:>3} "
                  + (f"{code:<4} " if baseline else "")
                  + f"{r['proc_s']:>7.2f} {r['rtf']:>6.2f} {r['ev_per_s']:>9.0f} "
                  f"{r['flow']:>6.2f} {r['velocity']:>6.2f} {r['pose']:>6.2f} {r['frames']:>6.2f} "
                  f"{r['pose_src']:>8.2f} {r['group_p50_ms']:>6.2f}ms {r['group_p95_ms']:>6.2f}ms "
                  + extra
                  + f"{r.get('error', ''):<20} " + " ".join(f"{t:.2f}" for t in r["runs"]),
                  flush=True)
