"""``evtrack.utils.claim_output_folder`` / ``remove_outputs``: a command's outputs in a folder
that may hold other things (an earlier run, the user's files, the command's own inputs)."""

from __future__ import annotations

import os
import signal
import time

import pytest

from evtrack.errors import ConfigError
from evtrack.utils import claim_output_folder, remove_outputs, terminate_as_interrupt

NAMES = ("results.md", "trajectories", "plots")


def test_new_folder_is_made_and_removed_again_up_to_the_first_one_made(tmp_path):
    out = tmp_path / "a" / "b" / "c"
    made = claim_output_folder(out, NAMES, overwrite=False)
    assert out.is_dir() and made == tmp_path / "a"
    (out / "trajectories").mkdir()
    (out / "trajectories" / "x.h5").write_text("half")
    remove_outputs(out, NAMES, made)
    assert not (tmp_path / "a").exists() and tmp_path.is_dir()


def test_earlier_outputs_are_refused_then_replaced_and_other_files_stay(tmp_path):
    out = tmp_path / "res"
    out.mkdir()
    (out / "results.md").write_text("old")
    (out / "plots").mkdir()
    (out / "mine.txt").write_text("mine")
    (out / ".results.md.tmp-abc.md").write_text("left by a killed write")
    with pytest.raises(ConfigError, match=r"earlier run \(results.md, plots/\).*--overwrite"):
        claim_output_folder(out, NAMES, overwrite=False)
    assert (out / "results.md").read_text() == "old"
    assert claim_output_folder(out, NAMES, overwrite=True) is None  # existed: never removed
    assert sorted(p.name for p in out.iterdir()) == ["mine.txt"]
    remove_outputs(out, NAMES, None)
    assert out.is_dir()


def test_an_output_place_that_is_a_folder_or_link_of_another_kind(tmp_path):
    out = tmp_path / "res"
    out.mkdir()
    (out / "results.md").mkdir()  # a stray folder where a file goes: replaced with overwrite
    target = tmp_path / "elsewhere"
    target.mkdir()
    (target / "keep.txt").write_text("keep")
    (out / "plots").symlink_to(target)  # a link is removed, never followed
    (out / "trajectories").symlink_to(tmp_path / "gone")  # broken: still an earlier output
    with pytest.raises(ConfigError, match="trajectories"):
        claim_output_folder(out, NAMES, overwrite=False)
    claim_output_folder(out, NAMES, overwrite=True)
    assert list(out.iterdir()) == [] and (target / "keep.txt").read_text() == "keep"


def test_inputs_among_the_outputs_are_refused_even_with_overwrite(tmp_path):
    out = tmp_path / "w"
    (out / "plots" / "seq").mkdir(parents=True)
    (out / "plots" / "seq" / "meta.yaml").write_text("x")
    for overwrite in (False, True):
        with pytest.raises(ConfigError, match=r"--benchmark .* lies in .*plots"):
            claim_output_folder(out, NAMES, overwrite,
                                inputs={"--benchmark": out / "plots" / "seq", "--config": None})
    assert (out / "plots" / "seq" / "meta.yaml").is_file()
    (out / "results.md").write_text("an input named like an output")
    with pytest.raises(ConfigError, match="input .*results.md"):
        claim_output_folder(out, NAMES, True, inputs={"input": out / "results.md"})
    assert (out / "results.md").is_file()
    # an input beside the outputs is fine
    claim_output_folder(tmp_path / "v", NAMES, False, inputs={"input": tmp_path / "v" / "x.h5"})


def test_bad_places(tmp_path):
    afile = tmp_path / "f"
    afile.write_text("x")
    with pytest.raises(ConfigError, match="not a folder"):
        claim_output_folder(afile, NAMES, overwrite=True)
    with pytest.raises(ConfigError, match="is a file, not a folder"):
        claim_output_folder(afile / "sub", NAMES, overwrite=True)
    broken = tmp_path / "broken"
    broken.symlink_to(tmp_path / "missing")
    with pytest.raises(ConfigError, match="broken symbolic link"):
        claim_output_folder(broken, NAMES, overwrite=True)
    if os.geteuid() != 0:  # root may write anywhere
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        with pytest.raises(ConfigError, match="not writable"):
            claim_output_folder(locked, NAMES, overwrite=True)


def test_terminate_as_interrupt_turns_sigterm_into_keyboard_interrupt():
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt), terminate_as_interrupt():
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the handler interrupts it at once
    assert signal.getsignal(signal.SIGTERM) == before


def test_output_folder_cleans_up_a_failed_block(tmp_path):
    from evtrack.utils import output_folder

    out = tmp_path / "new" / "res"
    with pytest.raises(RuntimeError), output_folder(out, NAMES, overwrite=False) as folder:
        (folder / "results.md").write_text("half")
        raise RuntimeError("failed")
    assert not (tmp_path / "new").exists()
    with output_folder(out, NAMES, overwrite=False) as folder:
        (folder / "results.md").write_text("done")
    assert (out / "results.md").read_text() == "done"
