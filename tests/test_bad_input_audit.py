"""Bad-input audit: every case here once ended in a traceback, a silent success, a misleading message or lost data.

The contract (README, "Commands"; docs/ci.md): one line on stderr, exit code 2, nothing overwritten or lost. The commands run
in-process (``matcap.cli.main``) and fail before any network or renderer runs, so the file is fast.
"""
from __future__ import annotations

import argparse
import json
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from matcap import imageio
from matcap.cli import main
from matcap.results import write_result

BUNDLED_NORMAL = Path(__file__).resolve().parents[1] / "networks" / "weights" / "normal_small.safetensors"


def run(args: list[str]) -> int:
    """``matcap ARGS`` in-process; usage errors (argparse) end in SystemExit, which is the same exit code."""
    try:
        return main(args)
    except SystemExit as exc:
        return exc.code


def one_line_error(capsys_or_capfd, needle: str, rc: int) -> str:
    captured = capsys_or_capfd.readouterr()
    assert rc == 2, (rc, captured.err)
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert len(lines) == 1 and needle in lines[0], captured.err
    assert "Traceback" not in captured.err
    return lines[0]


def photos(folder: Path, n: int = 3, size: int = 24) -> Path:
    """n 8-bit images of a lit disc, with mask.png."""
    folder.mkdir(parents=True, exist_ok=True)
    yy, xx = np.mgrid[0:size, 0:size]
    inside = (xx - size / 2) ** 2 + (yy - size / 2) ** 2 < (0.4 * size) ** 2
    for i in range(n):
        imageio.write_png(folder / f"img_{i:02d}.png", np.where(inside[..., None], 0.2 + 0.2 * i, 0.05) * np.ones(3),
                          bits=8)
    imageio.write_png(folder / "mask.png", inside.astype(np.float32), bits=8)
    return folder


@pytest.fixture
def result(tmp_path, sphere_maps) -> Path:
    return write_result(sphere_maps(16), tmp_path / "result")


def capture_args(folder: Path, out: Path, *extra: str) -> list[str]:
    return ["capture", str(folder), "--out", str(out), "--weights", str(BUNDLED_NORMAL), "--quiet", *extra]


# ------------------------------------------------------------------------------------------------ capture


def test_capture_bogus_device_is_one_line(tmp_path, capsys):
    rc = run(capture_args(photos(tmp_path / "p"), tmp_path / "out", "--device", "bogus"))
    one_line_error(capsys, "--device 'bogus': not a torch device", rc)


@pytest.mark.parametrize("extra, needle", [
    (["--pixel-samples", "0"], "--pixel-samples must be at least 1"),
    (["--seed", "-1"], "--seed must be 0 or more"),
    (["--relight", "missing.exr"], "no such environment map"),
    (["--relight", "ENV", "--spp", "0"], "--spp must be between 1 and 65536, got 0"),
    (["--export", "tex", "--preset", "bogus"], "--preset: invalid choice: 'bogus'"),
])
def test_capture_bad_options_fail_before_writing_a_result(tmp_path, capsys, extra, needle):
    extra = [str(tmp_path / "missing.exr") if e == "missing.exr" else e for e in extra]
    extra = [str(Path(__file__).resolve().parents[1] / "matcap/data/envmaps/studio_small_03.exr") if e == "ENV" else e
             for e in extra]
    out = tmp_path / "out"
    rc = run(capture_args(photos(tmp_path / "p"), out, "--max-side", "16", *extra))
    one_line_error(capsys, needle, rc)
    assert not out.exists()  # failed before the networks ran and the result was written


@pytest.mark.parametrize("where", ["same", "parent"])
def test_capture_overwrite_never_replaces_the_photos(tmp_path, capsys, where):
    folder = photos(tmp_path / "p" / "photos")
    out = folder if where == "same" else folder.parent
    rc = run(capture_args(folder, out, "--max-side", "16", "--overwrite"))
    one_line_error(capsys, "would replace the input", rc)
    assert sorted(p.name for p in folder.iterdir()) == ["img_00.png", "img_01.png", "img_02.png", "mask.png"]


def test_published_checkpoint_that_is_a_plain_pickle_gives_one_line(tmp_path):
    bad = tmp_path / "nml.pytmodel"
    bad.write_bytes(pickle.dumps({"a": 1}, protocol=4))  # torch warns about protocol 4 before failing
    # a subprocess: pytest would record the UserWarning instead of printing it
    r = subprocess.run([sys.executable, "-m", "matcap", "weights", "import", str(bad), "--out", str(tmp_path / "w")],
                       capture_output=True, text=True, timeout=300, check=False)
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert "not a loadable weights-only PyTorch file" in lines[0]


# ------------------------------------------------------------------------------------------------ result folders


def test_result_with_capture_json_that_is_not_an_object(result, tmp_path, capsys):
    (result / "capture.json").write_text("[1, 2]")
    rc = run(["export", str(result), "--out", str(tmp_path / "tex")])
    one_line_error(capsys, "capture.json: expected a JSON object, got a list", rc)


def test_result_with_all_black_mask_is_refused(result, tmp_path, capsys):
    imageio.write_png(result / "mask.png", np.zeros((16, 16), np.float32), bits=8)
    rc = run(["relight", str(result), "--out", str(tmp_path / "r"), "--size", "8", "--spp", "1", "--quiet"])
    one_line_error(capsys, "the mask is empty", rc)
    assert not (tmp_path / "r").exists()


def test_result_with_inf_in_height_exr_is_refused(result, tmp_path, capsys):
    height = np.zeros((16, 16), np.float32)
    height[8, 8] = np.inf  # inside the sphere's mask
    imageio.write_exr(result / "height.exr", height)
    rc = run(["export", str(result), "--out", str(tmp_path / "tex")])
    one_line_error(capsys, "height.exr: 1 pixel(s) are NaN or Inf", rc)
    assert not (tmp_path / "tex").exists()


def test_truncated_exr_is_one_line_and_names_the_damage(result, tmp_path, capfd):
    data = (result / "normal.exr").read_bytes()
    (result / "normal.exr").write_bytes(data[: len(data) // 2])
    rc = run(["export", str(result), "--out", str(tmp_path / "tex")])
    captured = capfd.readouterr()  # fd level: the OpenEXR core writes to fds 1 and 2 itself
    assert rc == 2
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert len(lines) == 1 and "cannot read EXR" in lines[0], captured.err
    assert "0 parts" not in lines[0]
    assert captured.out.strip() == ""


def test_gallery_overwrite_never_replaces_its_source(result, capsys):
    rc = run(["gallery", str(result), "--out", str(result), "--overwrite", "--size", "8", "--orbit", "0",
               "--spp", "1", "--quiet"])
    one_line_error(capsys, "would replace the input", rc)
    assert (result / "normal.exr").is_file() and (result / "capture.json").is_file()


# ------------------------------------------------------------------------------------------------ eval


@pytest.fixture
def diligent(tmp_path) -> Path:
    from matcap.evaluation import toy

    n, m = toy.sphere_normals(24)
    lights = toy.cone_lights(6, 40)
    toy.write_diligent_object(tmp_path / "ds" / "sphere", toy.render_lambertian(n, m, lights), m, n, lights)
    return tmp_path / "ds"


def test_eval_does_not_replace_earlier_results_without_overwrite(diligent, tmp_path, capsys):
    out = tmp_path / "report"
    assert run(["eval", str(diligent), "--out", str(out), "--quiet"]) == 0
    before = (out / "results.md").read_text()
    capsys.readouterr()
    rc = run(["eval", str(diligent), "--method", "flat", "--out", str(out), "--quiet"])
    one_line_error(capsys, "already holds files; pass --overwrite", rc)
    assert (out / "results.md").read_text() == before
    assert run(["eval", str(diligent), "--method", "flat", "--out", str(out), "--overwrite", "--quiet"]) == 0
    assert "`flat`" in (out / "results.md").read_text()


@pytest.mark.parametrize("extra, needle", [
    (["--max-images", "3", "--seed", "-1"], "argument --seed: must be at least 0"),
    (["--method", "sdm-unips", "--device", "bogus"], "not a torch device"),
    (["--json", "DIR"], "is a folder; give a file name"),
    (["--markdown", "EXISTING"], "already exists; pass --overwrite to replace it"),
])
def test_eval_bad_options(diligent, tmp_path, capsys, extra, needle):
    existing = tmp_path / "earlier.md"
    existing.write_text("an earlier table")
    extra = [str(tmp_path) if e == "DIR" else str(existing) if e == "EXISTING" else e for e in extra]
    one_line_error(capsys, needle, run(["eval", str(diligent), "--quiet", *extra]))
    assert existing.read_text() == "an earlier table"


# ------------------------------------------------------------------------------------------------ synth, train


def test_synth_params_json_that_is_not_an_object(tmp_path, capsys):
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "synth_params.json").write_text("[1]")
    rc = run(["synth", "--out", str(tmp_path / "d"), "--scenes", "1", "--resolution", "8", "--quiet"])
    one_line_error(capsys, "synth_params.json: expected a JSON object, got a list", rc)


def test_synth_refuses_to_mix_scenes_into_a_capture_result(result, capsys):
    rc = run(["synth", "--out", str(result), "--scenes", "1", "--resolution", "8", "--quiet"])
    one_line_error(capsys, "not part of a `matcap synth` dataset", rc)
    assert not list(result.glob("scene_*")) and not (result / "synth_params.json").exists()


def test_train_refuses_to_replace_an_earlier_run(tmp_path, capsys):
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "checkpoint.pt").write_bytes(b"an earlier run's checkpoint")
    rc = run(["train", "--data", str(tmp_path), "--preset", "tiny", "--out", str(folder), "--steps", "1", "--quiet"])
    one_line_error(capsys, "holds an earlier run (checkpoint.pt); pass --resume", rc)
    assert (folder / "checkpoint.pt").read_bytes() == b"an earlier run's checkpoint"


@pytest.mark.parametrize("extra, needle", [
    (["--steps", "0"], "--steps must be at least 1, got 0"),
    (["--batch", "0"], "--batch must be at least 1, got 0"),
    (["--resolution", "0"], "--resolution must be at least 1"),
    (["--log-every", "0"], "--log-every must be at least 1"),
    (["--threads", "-1"], "--threads must be at least 0"),
    (["--min-images", "5", "--max-images", "2"], "must not be below --min-images"),
    (["--min-crop", "2"], "--min-crop must be a fraction in (0, 1]"),
    (["--drop-mask-prob", "2"], "--drop-mask-prob must be a probability"),
    (["--device", "bogus"], "not a torch device"),
])
def test_train_bad_settings_are_one_line(tmp_path, capsys, extra, needle):
    rc = run(["train", "--data", str(tmp_path), "--preset", "tiny", "--out", str(tmp_path / "run"), "--quiet", *extra])
    one_line_error(capsys, needle, rc)


# ------------------------------------------------------------------------------------------------ models, reference


def test_models_install_name_is_a_file_name_not_a_path(tmp_path):
    from matcap.errors import MatcapError
    from matcap.models import install

    with pytest.raises(MatcapError, match="--name"):
        install(BUNDLED_NORMAL, "../escaped", folder=tmp_path / "weights")
    assert not (tmp_path / "escaped.safetensors").exists()


@pytest.fixture
def case(tmp_path) -> Path:
    np.savez(tmp_path / "case.npz", images=np.zeros((2, 8, 8, 3)), mask=np.ones((8, 8)), normal=np.zeros((8, 8, 3)))
    meta = {"salt": "x", "canonical_resolution": 8, "decoder_resolution": 8, "pixel_samples": 4}
    (tmp_path / "case.json").write_text(json.dumps(meta))
    return tmp_path / "case.npz"


@pytest.mark.parametrize("extra, needle", [
    (["--threads", "-1"], "--threads must be 0"),
    (["--device", "bogus"], "not a torch device"),
])
def test_reference_check_bad_options(case, capsys, extra, needle):
    one_line_error(capsys, needle, run(["reference-check", str(case), *extra]))


def test_reference_check_junk_npz_names_the_file(case, capsys):
    case.write_bytes(b"junk")
    line = one_line_error(capsys, "case.npz: not a readable .npz case file", run(["reference-check", str(case)]))
    assert "allow_pickle" not in line


def test_unwritable_output_is_refused_before_the_work(tmp_path, capsys, monkeypatch):
    import os

    import matcap.results

    real_access = os.access
    monkeypatch.setattr(matcap.results.os, "access",
                        lambda p, mode: False if Path(p) == tmp_path / "ro" else real_access(p, mode))
    (tmp_path / "ro").mkdir()
    rc = run(capture_args(photos(tmp_path / "p"), tmp_path / "ro" / "out", "--max-side", "16"))
    one_line_error(capsys, "cannot write in", rc)


def test_env_map_with_nan_or_inf_is_one_line_exit_2(result, tmp_path, capsys):
    from matcap import imageio
    from matcap.cli import main

    env = np.ones((8, 16, 3), np.float32)
    env[2, 3, 1] = np.inf
    path = tmp_path / "broken.exr"
    imageio.write_exr(path, env)
    assert main(["relight", str(result), "--env", str(path), "--out", str(tmp_path / "lit"), "--spp", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "NaN or Inf" in err[0], err
    assert not (tmp_path / "lit").exists()


def test_warnings_are_one_line_on_the_command_line(monkeypatch):
    import warnings

    from matcap import cli

    line = cli._one_line_warning("a texel is negative,\n clamped to 0", UserWarning, "x.py", 3, "code")
    assert line == "matcap: warning: a texel is negative, clamped to 0\n"
    during = []
    monkeypatch.delenv("MATCAP_DEBUG", raising=False)
    parser = cli.build_parser()
    monkeypatch.setattr(cli, "build_parser", lambda: parser)
    monkeypatch.setattr(parser, "parse_args", lambda argv: argparse.Namespace(
        func=lambda args: during.append(warnings.formatwarning) or 0, command="relight"))
    before = warnings.formatwarning
    assert cli.main([]) == 0
    assert during == [cli._one_line_warning]  # one line while a command runs
    assert warnings.formatwarning is before  # and restored for the host process


def test_weights_import_names_the_mistake(tmp_path, capsys):
    folder = tmp_path / "ckpts"
    folder.mkdir()
    ours = tmp_path / "normal_small.safetensors"
    ours.write_bytes(b"0" * 64)
    for arg, needle in ((folder, "is a folder; give the published checkpoint files"),
                        (ours, "matcap's own weights need no import")):
        assert main(["weights", "import", str(arg), "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0], err


# ---- a new user's environment variables


def test_unknown_forced_mitsuba_variant_is_one_line(tmp_path, sphere_maps):
    pytest.importorskip("mitsuba")
    write_result(sphere_maps(8), tmp_path / "result")
    env = {**__import__("os").environ, "MATCAP_MITSUBA_VARIANT": "llvm_rgb"}
    r = subprocess.run([sys.executable, "-m", "matcap", "relight", str(tmp_path / "result"), "--quiet"],
                       capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "MATCAP_MITSUBA_VARIANT='llvm_rgb' is not a Mitsuba variant" in lines[0], r.stderr


def test_bad_memory_setting_is_one_line(tmp_path, monkeypatch, capsys):
    from conftest import sphere_photos

    photos = sphere_photos(tmp_path / "photos", h=8, w=8, n=2)
    monkeypatch.setenv("MATCAP_MEMORY_GB", "lots")
    rc = run(["capture", str(photos), "--out", str(tmp_path / "o"), "--weights", str(BUNDLED_NORMAL)])
    one_line_error(capsys, "MATCAP_MEMORY_GB must be a number of gigabytes, got 'lots'", rc)
