"""``evtrack convert`` through evtrack.cli.main."""

from __future__ import annotations

import pytest

from evtrack.cli import main
from evtrack.events import Events
from evtrack.io import detect_format, read_events, write_events


@pytest.mark.parametrize(("src", "dst"), [("h5", "txt"), ("txt", "npz"), ("npz", "h5"),
                                          ("h5", "h5"), ("txt", "h5")])
def test_convert_between_writable_formats(tmp_path, events_factory, src, dst, capsys):
    ev = events_factory(3000, seed=1)
    write_events(tmp_path / f"in.{src}", ev)
    out = tmp_path / f"out.{dst}"
    assert main(["convert", str(tmp_path / f"in.{src}"), str(out), "--window-ms", "2"]) == 0
    assert read_events(out) == ev
    assert "wrote 3000 events" in capsys.readouterr().out


def test_convert_real_raw_to_compressed_hdf5(tmp_path, evt3_file):
    out = tmp_path / "evt3.h5"
    assert main(["convert", str(evt3_file), str(out), "--compression", "lzf", "--quiet"]) == 0
    assert read_events(out) == read_events(evt3_file)


def test_convert_options(tmp_path, events_factory):
    ev = events_factory(100, seed=2)
    write_events(tmp_path / "a.txt", ev)
    assert main(["convert", str(tmp_path / "a.txt"), str(tmp_path / "b.data"), "--to", "npz",
                 "--compress", "--sensor-size", "700", "500"]) == 0
    assert detect_format(tmp_path / "b.data") == "npz"
    assert read_events(tmp_path / "b.data").sensor_size == (700, 500)


def test_convert_refuses_to_overwrite_unless_asked(tmp_path, events_factory, capsys):
    ev = events_factory(50, seed=3)
    write_events(tmp_path / "a.h5", ev)
    write_events(tmp_path / "b.txt", events_factory(10, seed=4))
    assert main(["convert", str(tmp_path / "a.h5"), str(tmp_path / "b.txt")]) == 1
    assert "exists; pass --overwrite" in capsys.readouterr().err
    assert main(["convert", str(tmp_path / "a.h5"), str(tmp_path / "b.txt"), "--overwrite"]) == 0
    assert read_events(tmp_path / "b.txt") == ev


def test_failed_conversion_leaves_no_output(tmp_path, capsys):
    lines = [f"0.{i:06d} 1 1 1" for i in range(1, 500)] + ["0.000001 1 1 1"]  # unsorted at end
    (tmp_path / "u.txt").write_text("\n".join(lines) + "\n")
    code = main(["convert", str(tmp_path / "u.txt"), str(tmp_path / "u.h5"),
                 "--sensor-size", "4", "4", "--window-ms", "0.1"])
    assert code == 1
    err = capsys.readouterr().err
    assert "u.txt" in err and "backwards" in err and "line 500" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["u.txt"]


def test_convert_errors_are_clean(tmp_path, capsys):
    ev = Events([1], [1], [5], [1], None)
    write_events(tmp_path / "n.txt", ev)
    assert main(["convert", str(tmp_path / "n.txt"), str(tmp_path / "n.h5")]) == 1
    assert "--sensor-size W H" in capsys.readouterr().err
    assert main(["convert", str(tmp_path / "n.txt"), str(tmp_path / "n.raw")]) == 1
    assert "writing RAW is not supported" in capsys.readouterr().err
    assert main(["convert", str(tmp_path / "missing.h5"), str(tmp_path / "x.h5")]) == 1
    assert "no such file" in capsys.readouterr().err
    assert not (tmp_path / "n.h5").exists() and not (tmp_path / "x.h5").exists()


def test_convert_help_explains_formats(capsys):
    with pytest.raises(SystemExit) as info:
        main(["convert", "--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    for word in ("hdf5", "text", "npz", "aedat4", "evt2", "evt3", "read only", "--window-ms"):
        assert word in out


def test_an_unwritable_output_is_one_line_not_a_traceback(tmp_path, events_factory, capsys,
                                                          monkeypatch):
    write_events(tmp_path / "a.h5", events_factory(50, seed=4))
    (tmp_path / "file.txt").write_text("a file, not a folder")
    out = tmp_path / "file.txt" / "b.h5"
    monkeypatch.delenv("EVTRACK_DEBUG", raising=False)
    assert main(["convert", str(tmp_path / "a.h5"), str(out), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("evtrack convert: error: ") and "Traceback" not in err
    assert "file.txt" in err and "EVTRACK_DEBUG=1" in err
    monkeypatch.setenv("EVTRACK_DEBUG", "1")  # the traceback when asked for
    with pytest.raises(OSError):
        main(["convert", str(tmp_path / "a.h5"), str(out), "--quiet"])


def test_a_format_against_the_extension_is_warned_about_and_hints_name_the_option(
        tmp_path, events_factory, capsys):
    write_events(tmp_path / "a.h5", events_factory(20, seed=5))
    assert main(["convert", str(tmp_path / "a.h5"), str(tmp_path / "b.h5"), "--to", "text",
                 "--quiet"]) == 0
    assert "writing text to" in capsys.readouterr().err
    assert detect_format(tmp_path / "b.h5") == "text"
    assert main(["convert", str(tmp_path / "a.h5"), str(tmp_path / "c.xyz"), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "or give --to" in err and "format=" not in err


def test_a_text_file_without_a_sensor_size_to_hdf5_names_the_option(tmp_path, capsys):
    (tmp_path / "nohdr.txt").write_text("0.001 1 1 1\n")
    assert main(["convert", str(tmp_path / "nohdr.txt"), str(tmp_path / "o.h5"),
                 "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "nohdr.txt" in err and "give --sensor-size W H" in err
    assert not (tmp_path / "o.h5").exists()
