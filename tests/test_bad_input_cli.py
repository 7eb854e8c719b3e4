"""Every command: a bad value ends as one line on stderr naming the option, the value and what
was expected, with exit 2 and no traceback (``--debug`` shows it)."""
from __future__ import annotations

import os

import numpy as np
import pytest

from pipelines.cli import main

NO_CUDA = True
try:
    import torch

    NO_CUDA = not torch.cuda.is_available()
except ImportError:  # pragma: no cover
    pass


def fails(args: list[str], capsys, *expected: str, code: int = 2) -> str:
    """Runs ``drape args``; asserts the exit status, one line without traceback, and the fragments."""
    status = main(args)
    captured = capsys.readouterr()
    err = captured.err
    assert status == code, (status, err, captured.out)
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for fragment in expected:
        assert fragment in err, f"{fragment!r} not in {err!r}"
    return err


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from data_manifest.synthetic import write_synthetic_dataset

    root = tmp_path_factory.mktemp("data")
    write_synthetic_dataset(root, splits={"train": 2, "test": 1}, frames_per_task=2)
    return root


# -- body ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("args, expected", [
    (["--set", "height=abc"], ["--set height must be numbers", "'abc'"]),
    (["--set", "height"], ["--set 'height' must be NAME=VALUE"]),
    (["--set", "heigth=0.5"], ["unknown shape parameter 'heigth' (did you mean height?)"]),
    (["--set", "height=nan"], ["--set height must be finite numbers"]),
    (["--joint", "left_shoulder=0,1"], ["--joint left_shoulder must have 3 numbers (got 2"]),
    (["--joint", "left_shoulder=0,1,x"], ["--joint left_shoulder must be numbers"]),
    (["--joint", "left_sholder=0,0,1"], ["unknown joint name 'left_sholder' (did you mean left_shoulder?)"]),
    (["--pose", "0,0,0"], ["--pose must have 60 numbers (got 3"]),
    (["--shape", "0.5,0.5"], ["--shape must have 6 numbers (got 2"]),
    (["--shape", "0.5,0.5,0.5,0.5,2,0.5"], ["height=2 is outside its range [0, 1]"]),
    (["--backend", "smpl"], ["--backend smpl needs --model-path"]),
    (["--preview", "x.jpg"], ["--preview must end in .png"]),
])
def test_body_bad_values_name_the_option(tmp_path, capsys, anny_body, args, expected):
    fails(["body", *args, "--out", str(tmp_path / "b.obj")], capsys, *expected)
    assert not (tmp_path / "b.obj").exists()


def test_body_output_paths(tmp_path, capsys, unwritable_dir):
    fails(["body", "--out", str(tmp_path / "b.stl")], capsys, "--out must end in .obj or .ply")
    (tmp_path / "d.obj").mkdir()
    fails(["body", "--out", str(tmp_path / "d.obj")], capsys, "is a directory; expected a file name")
    (tmp_path / "f").write_text("x")
    fails(["body", "--out", str(tmp_path / "f" / "b.obj")], capsys, "--out", "/f' is a file; expected a directory")
    fails(["body", "--out", str(unwritable_dir / "b.obj")], capsys, "--out")


@pytest.mark.skipif(not NO_CUDA, reason="needs a machine without CUDA")
@pytest.mark.parametrize("command", [["body", "--out", "{tmp}/b.obj"], ["train", "baseline", "--data", "{data}", "--out", "{tmp}/run"],
                                     ["evaluate", "{tmp}", "--data", "{data}"],
                                     ["predict", "{tmp}", "--style", "0", "--out", "{tmp}/p.obj"]])
def test_device_cuda_without_cuda(tmp_path, capsys, dataset, command):
    args = [a.format(tmp=tmp_path, data=dataset) for a in command] + ["--device", "cuda"]
    fails(args, capsys, "--device 'cuda': torch finds no CUDA device on this machine")
    fails(args[:-1] + ["tpu"], capsys, "--device must be cpu, cuda or cuda:N (got 'tpu')")


# -- train --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("config, expected", [
    ("lf: {lr: [1e-4\n", "is not valid YAML at line"),
    ("- lf\n", "must map stage names"),
    ("lff: {lr: 1e-4}\n", "'lff' is not a training stage (did you mean lf?)"),
    ("lf: {lrr: 1e-4}\n", "lf.lrr is not a setting (did you mean lr?)"),
    ("lf: {lr: -1}\n", "lf.lr must be a finite number > 0 (got -1)"),
    ("lf: {lr: .nan}\n", "lf.lr must be a finite number > 0 (got nan)"),
    ("hf: {epochs: 2.5}\n", "hf.epochs must be an integer >= 0 (got 2.5)"),
    ("hf: {stacked: 1}\n", "hf.stacked must be true or false (got 1)"),
    ("model: {canonical_repeat: -1}\n", "model.canonical_repeat must be an integer >= 0 (got -1)"),
    ("model: {use_canonical_split: 0}\n", "model.use_canonical_split must be true or false (got 0)"),
    ("lf: 3\n", "lf must be a mapping of settings"),
    ("lf: {lr: -1e-4}\n", "lf.lr must be a finite number > 0 (got -0.0001)"),
])
def test_train_config_errors_name_the_file_and_field(tmp_path, capsys, dataset, config, expected):
    path = tmp_path / "hyper.yaml"
    path.write_text(config)
    fails(["train", "tailornet", "--data", str(dataset), "--out", str(tmp_path / "run"), "--config", str(path)],
          capsys, f"--config {path}", expected)
    assert not (tmp_path / "run").exists(), "nothing is written before the options are checked"


@pytest.mark.parametrize("args, expected", [
    (["--epochs", "0"], "--epochs must be an integer >= 1 (got 0)"),
    (["--prototypes", "0"], "--prototypes must be an integer >= 1 (got 0)"),
    (["--seed", "-1"], "--seed must be an integer >= 0 (got -1)"),
    (["--config", "missing.yaml"], "--config: hyper-parameter file not found: missing.yaml"),
])
def test_train_bad_options(tmp_path, capsys, dataset, args, expected):
    fails(["train", "baseline", "--data", str(dataset), "--out", str(tmp_path / "run"), *args], capsys, expected)


def test_train_data_and_out_problems(tmp_path, capsys, dataset, unwritable_dir):
    fails(["train", "baseline", "--data", str(tmp_path / "nope"), "--out", str(tmp_path / "run")], capsys,
          "dataset directory", "does not exist")
    (tmp_path / "file").write_text("x")
    fails(["train", "baseline", "--data", str(dataset), "--out", str(tmp_path / "file")], capsys,
          "--out", "is a file; expected a directory")
    fails(["train", "baseline", "--data", str(dataset), "--out", str(dataset)], capsys, "is the dataset directory")
    fails(["train", "baseline", "--data", str(dataset), "--out", str(unwritable_dir / "run")], capsys, "--out")


# -- evaluate, predict ----------------------------------------------------------------------------


def test_evaluate_bad_input(tmp_path, capsys, dataset):
    run = tmp_path / "run"
    run.mkdir()
    fails(["evaluate", str(tmp_path / "nope"), "--data", str(dataset)], capsys, "RUN", "is not a directory")
    fails(["evaluate", str(run), "--data", str(dataset), "--renders", "-1"], capsys, "--renders must be an integer >= 0")
    fails(["evaluate", str(run), "--data", str(dataset), "--postprocess-frames", "-2"], capsys,
          "--postprocess-frames must be an integer >= 0")
    fails(["evaluate", str(run), "--data", str(dataset), "--accuracy-report", "no.json"], capsys,
          "--accuracy-report 'no.json' does not exist")
    (tmp_path / "file").write_text("x")
    fails(["evaluate", str(run), "--data", str(dataset), "--out", str(tmp_path / "file")], capsys,
          "--out", "is a file; expected a directory")
    fails(["evaluate", str(run), "--data", str(dataset)], capsys, "no trained model in", "run drape train first")
    (run / "baseline_model.pt").write_bytes(b"not a checkpoint")
    fails(["evaluate", str(run), "--data", str(dataset)], capsys, "baseline_model.pt' is not a readable baseline checkpoint")


def test_predict_bad_input(tmp_path, capsys, anny_body, unwritable_dir):
    run = tmp_path / "run"
    run.mkdir()
    out = str(tmp_path / "p.obj")
    fails(["predict", str(tmp_path / "nope"), "--style", "0", "--out", out], capsys, "RUN", "is not a directory")
    fails(["predict", str(run), "--style", "0", "--out", str(tmp_path / "p.stl")], capsys, "--out must end in .obj or .ply")
    (tmp_path / "dir.obj").mkdir()
    fails(["predict", str(run), "--style", "0", "--out", str(tmp_path / "dir.obj")], capsys, "--out", "is a directory")
    fails(["predict", str(run), "--style", "0", "--out", str(unwritable_dir / "p.obj")], capsys, "--out")
    fails(["predict", str(run), "--style", "0", "--out", out], capsys, "no tailornet model in", "run drape train first")
    fails(["predict", str(run), "--style", "0", "--out", out, "--learner", "gcvae"], capsys,
          "--learner gcvae is trained on a static set and predicts no drape", "drape sample RUN")
    (run / "tailornet_model.pt").write_bytes(b"not a checkpoint")
    np.savez(run / "template.npz", faces=np.zeros((1, 3), np.int32))
    fails(["predict", str(run), "--style", "0", "--out", out, "--shape", "0.5,0.5,0.5,0.5,1.5,0.5"], capsys,
          "--shape: height=1.5 is outside its range [0, 1]")
    fails(["predict", str(run), "--style", "0", "--out", out, "--shape", "0.5,0.5"], capsys,
          "--shape must have 6 values, got 2")
    fails(["predict", str(run), "--style", "0", "--out", out, "--pose", "x"], capsys, "--pose must be numbers")
    fails(["predict", str(run), "--style", "0", "--out", out, "--pose", str(tmp_path / "p.npy")], capsys,
          "--pose", "no such .npy file")
    fails(["predict", str(run), "--style", "0", "--out", out], capsys,
          "tailornet_model.pt' is not a readable tailornet checkpoint")


# -- dataset export / info / validate, quickstart, the debug switch --------------------------------


def test_export_bad_input(tmp_path, capsys, dataset, unwritable_dir):
    base = ["dataset", "export", str(dataset)]
    fails(base + ["--task", "train-0001", "--format", "obj", "--out", str(tmp_path / "o")], capsys,
          "task 'train-0001' has no shard", "did you mean train-001?")
    fails(base + ["--task", "../x", "--format", "obj", "--out", str(tmp_path / "o")], capsys, "task id must be")
    (tmp_path / "file").write_text("x")
    fails(base + ["--task", "train-000", "--format", "obj", "--out", str(tmp_path / "file")], capsys,
          "--out", "is a file; obj writes one file per frame into a directory")
    fails(base + ["--task", "train-000", "--format", "pc2", "--out", str(tmp_path)], capsys,
          "--out", "is a directory; pc2 writes one file")
    fails(base + ["--task", "train-000", "--format", "pc2", "--out", str(tmp_path / "a.pc2"), "--sample-rate", "nan"],
          capsys, "--sample-rate must be a finite number > 0 (got nan)")
    fails(base + ["--task", "train-000", "--format", "obj", "--out", str(unwritable_dir / "o")], capsys, "--out")
    fails(["dataset", "export", str(tmp_path / "none"), "--task", "t", "--format", "obj", "--out", str(tmp_path / "o")],
          capsys, "does not exist")


def test_missing_directories_exit_2(tmp_path, capsys):
    fails(["dataset", "info", str(tmp_path / "none")], capsys, "dataset directory", "does not exist")
    fails(["dataset", "validate", str(tmp_path / "none")], capsys, "does not exist")
    (tmp_path / "empty").mkdir()
    fails(["dataset", "info", str(tmp_path / "empty")], capsys, "manifest.json' does not exist")


def test_quickstart_checks_its_options_before_simulating(tmp_path, capsys):
    fails(["quickstart", "--out", str(tmp_path / "q"), "--epochs", "0"], capsys, "--epochs must be an integer >= 1")
    assert not (tmp_path / "q").exists()


def test_argparse_errors_and_the_debug_switch(tmp_path, capsys, dataset):
    with pytest.raises(SystemExit) as exc:
        main(["train", "baseline", "--data", str(dataset), "--out", str(tmp_path), "--epochs", "x"])
    assert exc.value.code == 2 and "--epochs: invalid int value: 'x'" in capsys.readouterr().err
    config = tmp_path / "h.yaml"
    config.write_text("lf: {lrr: 1}\n")
    args = ["train", "baseline", "--data", str(dataset), "--out", str(tmp_path / "r"), "--config", str(config)]
    fails(args, capsys, "lf.lrr is not a setting")
    assert main(args + ["--debug"]) == 2
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err and "UsageError" in err and err.rstrip().endswith(
        "(did you mean lr?); expected one of batch_size, dropout, epochs, hidden_size, lr, weight_decay")
    os.environ["DRAPE_DEBUG"] = "1"
    try:
        assert main(args) == 2
        assert "Traceback" in capsys.readouterr().err
    finally:
        del os.environ["DRAPE_DEBUG"]


def test_internal_errors_are_one_line_with_a_hint(capsys, monkeypatch):
    import pipelines.info as info

    def broken(args):
        raise TypeError("unsupported operand")

    monkeypatch.setattr(info, "run", broken)
    fails(["info"], capsys, "drape info: error: internal error: TypeError: unsupported operand",
          "rerun with --debug", code=1)
