"""evtrack sets OMP_WAIT_POLICY=PASSIVE only when it can take effect and the user left it unset."""

from __future__ import annotations

import os
import subprocess
import sys

from evtrack.runtime.openmp_wait import WAIT_POLICY_VARIABLE, prefer_passive_wait, wait_policy


def test_sets_passive_when_unset_and_torch_not_loaded():
    env: dict[str, str] = {}
    assert prefer_passive_wait(env, {}) is True
    assert env == {WAIT_POLICY_VARIABLE: "PASSIVE"}


def test_keeps_the_users_setting():
    env = {WAIT_POLICY_VARIABLE: "ACTIVE"}
    assert prefer_passive_wait(env, {}) is False
    assert env == {WAIT_POLICY_VARIABLE: "ACTIVE"}


def test_leaves_it_alone_once_torch_is_loaded():
    env: dict[str, str] = {}
    assert prefer_passive_wait(env, {"torch": object()}) is False
    assert env == {}


def _policy_after(code: str, **extra: str) -> str:
    env = {k: v for k, v in os.environ.items() if k != WAIT_POLICY_VARIABLE} | extra
    out = subprocess.run([sys.executable, "-c", code + "; import os; "
                          f"print(os.environ.get('{WAIT_POLICY_VARIABLE}', 'unset'))"],
                         env=env, capture_output=True, text=True, check=True)
    return out.stdout.strip().splitlines()[-1]


def test_importing_evtrack_first_sets_it_for_the_process():
    assert _policy_after("import evtrack") == "PASSIVE"
    assert _policy_after("import evtrack", OMP_WAIT_POLICY="ACTIVE") == "ACTIVE"
    assert _policy_after("import torch, evtrack") == "unset"


def test_wait_policy_reports_the_environment(monkeypatch):
    monkeypatch.delenv(WAIT_POLICY_VARIABLE, raising=False)
    assert wait_policy() == "default"
    monkeypatch.setenv(WAIT_POLICY_VARIABLE, "PASSIVE")
    assert wait_policy() == "PASSIVE"
