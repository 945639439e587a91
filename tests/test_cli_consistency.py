"""The command-line interface as a new user meets it: one name per option across commands, defaults
and choices shown by --help, a default --out outside the data folder."""
from __future__ import annotations

import subprocess
import sys

import pytest

from matcap.cli import main


def help_text(capsys, *argv: str) -> str:
    with pytest.raises(SystemExit) as exit_:
        main([*argv, "--help"])
    assert exit_.value.code == 0
    return " ".join(capsys.readouterr().out.split())  # argparse wraps lines: compare with single spaces


@pytest.mark.parametrize("command", ["capture", "relight", "gallery", "synth", "train", "eval"])
def test_every_command_takes_quiet(capsys, command):
    assert "--quiet" in help_text(capsys, command)


def test_synth_keeps_no_progress_as_a_hidden_alias(capsys):
    text = help_text(capsys, "synth")
    assert "--no-progress" not in text and "--quiet no progress output" in text
    from matcap.cli import build_parser

    args = build_parser().parse_args(["synth", "--out", "d", "--scenes", "1", "--no-progress"])
    assert args.quiet is True


def test_capture_help_shows_choices_and_defaults(capsys):
    text = help_text(capsys, "capture")
    assert "--preset {gltf,unreal,unity-hdrp,blender}" in text and "(default gltf" in text
    assert "--relight / --point renders (default 16)" in text
    assert "default: ./PHOTOS-matcap" in text


def test_models_help_has_a_description_and_train_resolution_help_agrees(capsys):
    text = help_text(capsys, "models")
    assert "List the installed models" in text and "by default" in text
    text = help_text(capsys, "train")
    assert "(default: 256)" in text and "on a CPU use 128 with --canonical-resolution 128" in text


def test_capture_without_out_writes_into_the_current_folder(tmp_path, tiny_weights):
    from conftest import sphere_photos

    photos = sphere_photos(tmp_path / "data" / "photos", h=16, w=16, n=2)
    work = tmp_path / "work"
    work.mkdir()
    r = subprocess.run([sys.executable, "-m", "matcap", "capture", str(photos), "--weights", str(tiny_weights),
                        "--quiet"], capture_output=True, text=True, timeout=600, cwd=work)
    assert r.returncode == 0, r.stderr
    assert (work / "photos-matcap" / "normal.exr").is_file()
    import os

    umask = os.umask(0)
    os.umask(umask)
    assert (work / "photos-matcap").stat().st_mode & 0o777 == 0o777 & ~umask  # like any new folder (was 0700)
    assert (work / "photos-matcap" / "normal.exr").stat().st_mode & 0o777 == 0o666 & ~umask
    assert sorted(p.name for p in (tmp_path / "data").iterdir()) == ["photos"]  # nothing beside the photos
