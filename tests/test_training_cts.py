"""The training CTs are named once in Python (``io.shared_data.TRAINING_CTS``); the training shell script repeats
them and must say the same, and no training CT may be held out."""

from __future__ import annotations

import os
import re
from pathlib import Path

from conftest import listing

from monai_rigidreg.io.shared_data import HELD_OUT_CTS, TRAINING_CTS, training_ct_paths

REPO = Path(__file__).resolve().parents[1]


def test_the_training_script_trains_on_the_package_s_training_cts():
    text = (REPO / "scripts" / "train_context_model.sh").read_text()
    block = re.search(r"TRAIN_CTS=\(([^)]*)\)", text)
    assert block is not None
    assert tuple(block.group(1).split()) == TRAINING_CTS
    assert not set(TRAINING_CTS) & set(HELD_OUT_CTS)


def test_training_ct_paths_keeps_the_order_and_skips_what_is_missing(tmp_path):
    for name in (TRAINING_CTS[2], TRAINING_CTS[0], HELD_OUT_CTS[0]):
        (tmp_path / f"{name}.nii.gz").write_bytes(b"")
    assert training_ct_paths(tmp_path) == [tmp_path / f"{TRAINING_CTS[0]}.nii.gz",
                                           tmp_path / f"{TRAINING_CTS[2]}.nii.gz"]


def test_benchmarks_label_every_training_ct_as_one():
    # the accuracy benchmarks head each CT's table "held out of training" or "TRAINING CT" from the package's list
    # (a stale copy once labelled the TCIA CTs held out); data-folder suffixes keep the label
    from benchmarks.bench_common import is_training_ct, training_mark

    for name in TRAINING_CTS:
        assert is_training_ct(name) and is_training_ct(f"{name}_rtk_ideal") and "TRAINING CT" in training_mark(name)
    for name in (*HELD_OUT_CTS, "my_own_ct", "head_tigre_ct_multi30"):
        assert not is_training_ct(name) and training_mark(name) == " (held out of training)"


def _fake_data(tmp_path):
    """A DATA folder with two simulated sets (one made from the abdomen CT, as make_training_data.sh does) and a
    SHARED folder naming the six real CTs (empty files: the fold's preparation only checks that they exist)."""
    import json

    data, shared = tmp_path / "data", tmp_path / "shared"
    shared.mkdir()
    for name in (*TRAINING_CTS, *HELD_OUT_CTS):
        (shared / f"{name}.nii.gz").write_bytes(b"")
    items = []
    for folder, phantom in (("abdomen", f"/x/{TRAINING_CTS[0]}.nii.gz"), ("synth_full", "synth")):
        (data / folder).mkdir(parents=True)
        (data / folder / "simulation.json").write_text(json.dumps({"config": {"phantom": phantom}}))
        for k in range(2):
            items.append({"fixed": f"{folder}/objects/obj{k}_simct.nii.gz", "moving": f"{folder}/cases/c{k}.nii.gz",
                          "moving_fov": f"{folder}/cases/c{k}_fov.nii.gz", "object": Path(phantom).name,
                          "params": [0.0] * 6})
    (data / "train.json").write_text(json.dumps({"training": items}))
    (data / "val_paper").mkdir()
    return data, shared


def _loco(tmp_path, hold, data, shared):
    import os
    import subprocess

    env = {**os.environ, "DATA": str(data), "SHARED": str(shared), "LOCO_DATA": str(tmp_path / "loco"),
           "PREPARE_ONLY": "1"}
    return subprocess.run(["bash", str(REPO / "scripts" / "train_loco.sh"), hold], env=env, capture_output=True,
                          text=True, timeout=120)


def test_a_loco_fold_trains_on_the_other_five_cts_without_the_pairs_simulated_from_its_held_out_ct(tmp_path):
    import json

    data, shared = _fake_data(tmp_path)
    hold = TRAINING_CTS[0]
    run = _loco(tmp_path, hold, data, shared)
    assert run.returncode == 0, run.stderr
    fold = json.loads((tmp_path / "loco" / hold / "train.json").read_text())["training"]
    assert [Path(it["fixed"]).parts[-3] for it in fold] == ["synth_full", "synth_full"]  # the abdomen set dropped
    assert all(Path(it[k]).is_absolute() and str(data.resolve()) in it[k] for it in fold
               for k in ("fixed", "moving", "moving_fov"))
    names = re.search(r'TRAIN_CT_NAMES="([^"]*)"', run.stdout).group(1).split()
    assert sorted(names) == sorted(n for n in (*TRAINING_CTS, *HELD_OUT_CTS) if n != hold)
    assert (tmp_path / "loco" / hold / "val_paper").resolve() == (data / "val_paper").resolve()
    # a fold holding out the head CT keeps every simulated pair and trains on the held-out pair's thorax
    other = _loco(tmp_path, HELD_OUT_CTS[1], data, shared)
    assert other.returncode == 0, other.stderr
    assert len(json.loads((tmp_path / "loco" / HELD_OUT_CTS[1] / "train.json").read_text())["training"]) == 4
    assert HELD_OUT_CTS[0] in re.search(r'TRAIN_CT_NAMES="([^"]*)"', other.stdout).group(1).split()


def test_a_loco_fold_refuses_an_unknown_ct_and_writes_nothing(tmp_path):
    data, shared = _fake_data(tmp_path)
    run = _loco(tmp_path, "my_ct", data, shared)
    assert run.returncode == 2 and "HOLD_OUT must be one of" in run.stderr
    assert not (tmp_path / "loco").exists()


def test_benchmarks_label_a_fold_s_training_cts_from_the_environment(monkeypatch):
    from benchmarks.bench_common import TRAINED_ON_ENV, is_training_ct, training_mark

    monkeypatch.setenv(TRAINED_ON_ENV, f"{HELD_OUT_CTS[0]} {TRAINING_CTS[1]}")
    assert is_training_ct(HELD_OUT_CTS[0]) and is_training_ct(TRAINING_CTS[1])
    assert not is_training_ct(TRAINING_CTS[0])  # the fold's held-out CT, a training CT of the shipped network
    assert "evaluated network" in training_mark(HELD_OUT_CTS[0])
    assert training_mark(TRAINING_CTS[0]) == " (held out of training)"


def test_the_training_script_takes_a_fold_s_ct_list_from_train_ct_names(tmp_path):
    import os
    import subprocess

    env = {**os.environ, "TRAIN_CT_NAMES": f"{HELD_OUT_CTS[0]} not_a_ct", "SHARED": str(tmp_path)}
    (tmp_path / f"{HELD_OUT_CTS[0]}.nii.gz").write_bytes(b"")
    run = subprocess.run(["bash", str(REPO / "scripts" / "train_context_model.sh"), str(tmp_path / "run"), "1"],
                         env=env, capture_output=True, text=True, timeout=60)
    assert run.returncode == 2 and "not_a_ct.nii.gz" in run.stderr  # the list it checks is TRAIN_CT_NAMES'
    assert TRAINING_CTS[0] not in run.stderr and not (tmp_path / "run").exists()


def test_a_loco_evaluation_refuses_an_unknown_ct_or_a_fold_without_checkpoint(tmp_path):
    import subprocess

    script = str(REPO / "scripts" / "eval_loco.sh")
    bad = subprocess.run(["bash", script, "my_ct"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "HOLD_OUT must be one of" in bad.stderr
    empty = subprocess.run(["bash", script, HELD_OUT_CTS[1], str(tmp_path / "run"), str(tmp_path / "out")],
                           capture_output=True, text=True, timeout=60)
    assert empty.returncode == 2 and "no checkpoint" in empty.stderr and not (tmp_path / "out").exists()


def test_the_main_run_evaluation_refuses_a_run_without_checkpoint_or_a_missing_baseline(tmp_path):
    """``scripts/eval_main_run.sh``: exit status 2 and nothing written (no results folder, nothing in scratch/) for
    a run folder without a checkpoint, and for a ``BASELINE`` that is not a file."""
    import os
    import subprocess

    script = str(REPO / "scripts" / "eval_main_run.sh")
    scratch_before = sorted(p.name for p in (REPO / "scratch").glob("*")) if (REPO / "scratch").is_dir() else []
    empty = subprocess.run(["bash", script, str(tmp_path / "run"), str(tmp_path / "out")], capture_output=True,
                           text=True, timeout=60)
    assert empty.returncode == 2 and "no checkpoint" in empty.stderr and not (tmp_path / "out").exists()
    _config_checkpoint(tmp_path / "run", 4)
    missing = subprocess.run(["bash", script, str(tmp_path / "run"), str(tmp_path / "out")], capture_output=True,
                             text=True, timeout=60, env={**os.environ, "BASELINE": str(tmp_path / "no.json")})
    assert missing.returncode == 2 and "no.json is not a file" in missing.stderr
    assert not (tmp_path / "out").exists()
    scratch_after = sorted(p.name for p in (REPO / "scratch").glob("*")) if (REPO / "scratch").is_dir() else []
    assert scratch_after == scratch_before


def test_the_training_script_prepares_without_training_and_refuses_a_used_folder_first(tmp_path):
    """``PREPARE_DATA_ONLY=1`` (what a new leave-one-CT-out fold runs before its pretraining): the training script's
    checks and the missing data, then exit 0 with nothing in the run folder; a folder holding a run is refused."""
    import os
    import subprocess

    data, shared = _fake_data(tmp_path)
    (data / "clinical").mkdir()
    (data / "clinical" / "dataset.json").write_text("{}")
    env = {**os.environ, "TRAIN_CT_NAMES": " ".join(TRAINING_CTS), "SHARED": str(shared), "DATA": str(data),
           "PREPARE_DATA_ONLY": "1"}
    script = str(REPO / "scripts" / "train_context_model.sh")
    fresh = subprocess.run(["bash", script, str(tmp_path / "run"), "1"], env=env, capture_output=True, text=True,
                           timeout=60)
    assert fresh.returncode == 0, fresh.stderr
    assert not (tmp_path / "run").exists()
    (tmp_path / "used").mkdir()
    (tmp_path / "used" / "history.json").write_text("[]")
    used = subprocess.run(["bash", script, str(tmp_path / "used"), "1"], env=env, capture_output=True, text=True,
                          timeout=60)
    assert used.returncode == 2 and "holds an earlier run" in used.stderr


def test_the_folds_script_takes_each_fold_up_where_it_stopped(tmp_path):
    import subprocess

    runs, results = tmp_path / "runs", tmp_path / "results"
    (results).mkdir()
    a, b, c, d = TRAINING_CTS[0], TRAINING_CTS[1], HELD_OUT_CTS[0], HELD_OUT_CTS[1]
    for ct, epochs in ((a, (3, 7)), (b, (12,)), (c, (12,))):
        (runs / ct / "models").mkdir(parents=True)
        for e in epochs:
            (runs / ct / "models" / f"checkpoint_checkpoint_epoch={e}.pt").write_bytes(b"")
    for kind in ("real_ct", "clinical_geometry"):  # b evaluated at the last epoch, c not yet
        (results / f"bench_{kind}_loco_{b}_e12_2026-12-06.txt").write_text("x")
    (results / f"bench_real_ct_loco_{a}_shipped_2026-12-06.txt").write_text("x")
    env = {**os.environ, "RUNS": str(runs), "RESULTS": str(results), "DRY_RUN": "1"}
    script = str(REPO / "scripts" / "loco_folds.sh")
    run = subprocess.run(["bash", script, "12", a, b, c, d], env=env, capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert lines == [
        f"loco_folds: {a}: newest checkpoint epoch 7 of 12; next: resume from epoch 7, then evaluate "
        "(the shipped network's rows: measured)",
        f"loco_folds: {b}: newest checkpoint epoch 12 of 12; next: done (the shipped network's rows: to measure)",
        f"loco_folds: {c}: newest checkpoint epoch 12 of 12; next: evaluate (the shipped network's rows: to measure)",
        f"loco_folds: {d}: newest checkpoint epoch 0 of 12; next: start, then evaluate "
        "(the shipped network's rows: to measure)"]
    bad = subprocess.run(["bash", script, "12", a, "my_ct"], env=env, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "my_ct" in bad.stderr and bad.stdout == ""
    zero = subprocess.run(["bash", script, "0"], env=env, capture_output=True, text=True, timeout=60)
    assert zero.returncode == 2 and "positive integer" in zero.stderr


def _training_script_env(tmp_path, **extra):
    """The training script's path and an environment over fake DATA (with its clinical datalist) and SHARED folders
    (``_fake_data``), the package's training CTs named, plus ``extra``."""
    data, shared = _fake_data(tmp_path)
    (data / "clinical").mkdir()
    (data / "clinical" / "dataset.json").write_text("{}")
    env = {**os.environ, "TRAIN_CT_NAMES": " ".join(TRAINING_CTS), "SHARED": str(shared), "DATA": str(data), **extra}
    return str(REPO / "scripts" / "train_context_model.sh"), env


def _python_stand_in(tmp_path):
    """A stand-in for ``python`` that writes its arguments, one a line, to a file and exits 0: the training script
    runs through its checks and its writes, then hands the stand-in what it would hand the bundle. Returns the file
    and the environment entries (``PATH``, ``ARGS_FILE``) that put the stand-in first."""
    shim = tmp_path / "bin"
    shim.mkdir()
    (shim / "python").write_text('#!/usr/bin/env bash\nprintf "%s\\n" "$@" > "$ARGS_FILE"\n')
    (shim / "python").chmod(0o755)
    args_file = tmp_path / "args.txt"
    return args_file, {"PATH": f"{shim}:{os.environ['PATH']}", "ARGS_FILE": str(args_file)}


def _orientation_args(args_file):
    """The sampler's orientation arguments the training script handed the stand-in (``_python_stand_in``)."""
    words = args_file.read_text().split("\n")
    return {k: words[words.index(k) + 1] for k in ("--train#dataset#orientation_prob",
                                                    "--train#dataset#orientation_max") if k in words}


def test_the_training_script_keeps_a_run_s_anatomy_stretch(tmp_path):
    """A run's ``ANATOMY_PROB`` is kept in its folder: another value is refused with exit status 2 and the folder
    left as it was; the same value passes the checks."""
    import subprocess

    script, base = _training_script_env(tmp_path, PREPARE_DATA_ONLY="1")
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "anatomy_prob").write_text("0.5\n")
    other = subprocess.run(["bash", script, str(run_dir), "1"], env={**base, "ANATOMY_PROB": "0.3"},
                           capture_output=True, text=True, timeout=60)
    assert other.returncode == 2 and "ANATOMY_PROB=0.5, not 0.3" in other.stderr
    assert (run_dir / "anatomy_prob").read_text() == "0.5\n" and len(list(run_dir.iterdir())) == 1
    same = subprocess.run(["bash", script, str(run_dir), "1"], env={**base, "ANATOMY_PROB": "0.50"},
                          capture_output=True, text=True, timeout=60)
    assert same.returncode == 0, same.stderr  # the same number written otherwise


def test_the_training_script_keeps_a_run_s_orientation_and_passes_it_to_the_sampler(tmp_path):
    """``ORIENTATION_PROB`` / ``ORIENTATION_MAX``: a new run records them in its folder (``orientation``, "PROB MAX")
    and hands both to the sampler (``--train#dataset#orientation_prob`` / ``_max``, read from a stand-in for
    ``python``); a folder's values are used where none are given, and where one of the two is left out; another
    value, a bad value, or ``ORIENTATION_MAX`` alone for a new run is refused with exit status 2, nothing written."""
    import subprocess

    args_file, stand_in = _python_stand_in(tmp_path)
    script, base = _training_script_env(tmp_path, **stand_in)

    def run(run_dir, *args, **env):
        args_file.unlink(missing_ok=True)
        return subprocess.run(["bash", script, str(run_dir), "1", *args], env={**base, **env}, capture_output=True,
                              text=True, timeout=60)

    def sampler_args():
        return _orientation_args(args_file)

    new = run(tmp_path / "new", ORIENTATION_PROB="0.5", ORIENTATION_MAX="20")
    assert new.returncode == 0, new.stderr
    assert (tmp_path / "new" / "orientation").read_text() == "0.5 20\n"
    assert sampler_args() == {"--train#dataset#orientation_prob": "0.5", "--train#dataset#orientation_max": "20"}
    resumed = run(tmp_path / "new", "--resume")  # the stand-in wrote no checkpoint: the check stops it first
    assert resumed.returncode == 2 and "no checkpoint" in resumed.stderr
    plain = run(tmp_path / "plain")
    assert plain.returncode == 0 and sampler_args() == {} and not (tmp_path / "plain" / "orientation").exists()
    kept = tmp_path / "kept"
    kept.mkdir()
    (kept / "orientation").write_text("0.5 20\n")
    before = listing(kept)
    other = run(kept, ORIENTATION_PROB="0.3", ORIENTATION_MAX="20", PREPARE_DATA_ONLY="1")
    assert other.returncode == 2 and "'0.5 20', not '0.3 20'" in other.stderr and listing(kept) == before
    bad = run(tmp_path / "bad", ORIENTATION_PROB="1.5")
    assert bad.returncode == 2 and "ORIENTATION_PROB must be in [0, 1]" in bad.stderr
    assert not (tmp_path / "bad").exists()
    same = run(kept, ORIENTATION_PROB="0.50", ORIENTATION_MAX="20.0")
    assert same.returncode == 0, same.stderr
    assert sampler_args()["--train#dataset#orientation_prob"] == "0.50"
    from_folder = run(kept)  # nothing asked: the folder's values
    assert from_folder.returncode == 0 and sampler_args() == {"--train#dataset#orientation_prob": "0.5",
                                                              "--train#dataset#orientation_max": "20"}
    max_only = run(kept, ORIENTATION_MAX="20")  # the probability left out: the folder's
    assert max_only.returncode == 0 and sampler_args()["--train#dataset#orientation_prob"] == "0.5"
    alone = run(tmp_path / "alone", ORIENTATION_MAX="30")
    assert alone.returncode == 2 and "without ORIENTATION_PROB" in alone.stderr
    assert not (tmp_path / "alone").exists()


def _config_checkpoint(run_dir, epoch):
    """``run_dir/models/checkpoint_checkpoint_epoch=<epoch>.pt`` holding the bundle context config's network (what
    the training script's ``--resume`` check accepts)."""
    import torch
    from monai.bundle import ConfigParser

    parser = ConfigParser()
    configs = REPO / "bundles" / "cbct_ct_rigid" / "configs"
    parser.read_config([str(configs / "train.json"), str(configs / "train_context.json")])
    (run_dir / "models").mkdir(parents=True, exist_ok=True)
    torch.save({"network": parser.get_parsed_content("network_def").state_dict()},
               run_dir / "models" / f"checkpoint_checkpoint_epoch={epoch}.pt")


def test_a_resumed_run_keeps_its_orientation(tmp_path):
    """A resumed run (a checkpoint of the config's network in its folder) refuses another orientation than its
    recorded one, and a turn asked of a run trained without one (exit status 2, the folder as it was)."""
    import subprocess

    script, base = _training_script_env(tmp_path, PREPARE_DATA_ONLY="1")
    runs = {}
    for name, recorded in (("turned", "0.5 20\n"), ("upright", None)):
        runs[name] = tmp_path / name
        _config_checkpoint(runs[name], 3)
        if recorded:
            (runs[name] / "orientation").write_text(recorded)
    before = {name: listing(d) for name, d in runs.items()}

    def run(name, **env):
        return subprocess.run(["bash", script, str(runs[name]), "9", "--resume"], env={**base, **env},
                              capture_output=True, text=True, timeout=300)

    other = run("turned", ORIENTATION_PROB="0.3")
    assert other.returncode == 2 and "'0.5 20', not '0.3 20'" in other.stderr
    asked = run("upright", ORIENTATION_PROB="0.5")
    assert asked.returncode == 2 and "'0 15', not '0.5 15'" in asked.stderr
    assert {name: listing(d) for name, d in runs.items()} == before


def test_a_resumed_run_changes_its_anatomy_stretch_only_when_asked(tmp_path):
    """A run trained without the stretch, resumed with ``ANATOMY_PROB=0.5``: refused (exit status 2, the way named,
    the folder as it was) unless ``CHANGE_ANATOMY=1``, which passes the checks; ``CHANGE_ANATOMY=1`` without
    ``--resume`` is refused."""
    import subprocess

    script, base = _training_script_env(tmp_path, PREPARE_DATA_ONLY="1", ANATOMY_PROB="0.5")
    run_dir = tmp_path / "run"
    _config_checkpoint(run_dir, 7)
    before = listing(run_dir)

    def run(*args, **env):
        return subprocess.run(["bash", script, str(run_dir), *args], env={**base, **env}, capture_output=True,
                              text=True, timeout=300)

    refused = run("9", "--resume")
    assert refused.returncode == 2 and "ANATOMY_PROB=0, not 0.5" in refused.stderr
    assert "CHANGE_ANATOMY=1" in refused.stderr
    new_run = run("9", CHANGE_ANATOMY="1")
    assert new_run.returncode == 2 and "--resume" in new_run.stderr
    changed = run("9", "--resume", CHANGE_ANATOMY="1")
    assert changed.returncode == 0, changed.stderr
    assert listing(run_dir) == before  # PREPARE_DATA_ONLY: checks only, nothing written


def test_a_resumed_run_changes_its_orientation_only_when_asked(tmp_path):
    """A run trained without the turn (its checkpoint at epoch 7), resumed with ``ORIENTATION_PROB=0.5
    ORIENTATION_MAX=30``: refused (exit status 2, the way named, the folder as it was) unless
    ``CHANGE_ORIENTATION=1``, which records the new values, a history line naming the first epoch that trains with
    them (8) and the values before ('0 15'), and hands them to the sampler; a later resume keeps them without the
    switch. ``CHANGE_ORIENTATION=1`` without ``--resume``, or with the run's own values, is refused."""
    import subprocess

    args_file, stand_in = _python_stand_in(tmp_path)
    script, base = _training_script_env(tmp_path, **stand_in)
    run_dir = tmp_path / "run"
    (run_dir / "models").mkdir(parents=True)
    (run_dir / "models" / "checkpoint_checkpoint_epoch=7.pt").write_bytes(b"")  # the stand-in checks nothing
    before = listing(run_dir)

    def run(folder, *args, **env):
        args_file.unlink(missing_ok=True)
        return subprocess.run(["bash", script, str(folder), "9", *args], env={**base, **env}, capture_output=True,
                              text=True, timeout=60)

    turn = {"ORIENTATION_PROB": "0.5", "ORIENTATION_MAX": "30"}
    refused = run(run_dir, "--resume", **turn)
    assert refused.returncode == 2 and "'0 15', not '0.5 30'" in refused.stderr
    assert "CHANGE_ORIENTATION=1" in refused.stderr and listing(run_dir) == before
    new_run = run(tmp_path / "new", CHANGE_ORIENTATION="1", **turn)
    assert new_run.returncode == 2 and "--resume" in new_run.stderr and not (tmp_path / "new").exists()
    changed = run(run_dir, "--resume", CHANGE_ORIENTATION="1", **turn)
    assert changed.returncode == 0, changed.stderr
    assert (run_dir / "orientation").read_text() == "0.5 30\n"
    assert (run_dir / "orientation_history").read_text() == "epoch 8: 0 15 -> 0.5 30\n"
    assert _orientation_args(args_file) == {"--train#dataset#orientation_prob": "0.5",
                                            "--train#dataset#orientation_max": "30"}
    unchanged = run(run_dir, "--resume", CHANGE_ORIENTATION="1", **turn)  # already the run's values
    assert unchanged.returncode == 2 and "CHANGE_ORIENTATION=1 changes" in unchanged.stderr
    kept = run(run_dir, "--resume")
    assert kept.returncode == 0 and _orientation_args(args_file)["--train#dataset#orientation_max"] == "30"
    assert (run_dir / "orientation_history").read_text() == "epoch 8: 0 15 -> 0.5 30\n"


def test_a_branched_run_holds_the_newest_checkpoint_and_the_run_s_records(tmp_path):
    """``scripts/branch_run.sh RUN NEW``: NEW gets RUN's newest checkpoint by epoch (12, not the later file 3), its
    records (history, data options) and ``branched_from``, not its older checkpoints or exported model; RUN stays as
    it was. An existing NEW or a RUN without a checkpoint: exit status 2, nothing written."""
    import subprocess

    run_dir = tmp_path / "run"
    (run_dir / "models").mkdir(parents=True)
    for epoch in (12, 3):  # epoch 3 written last
        (run_dir / "models" / f"checkpoint_checkpoint_epoch={epoch}.pt").write_text(f"epoch {epoch}")
    (run_dir / "models" / "model.pt").write_text("exported")
    for name, text in (("history.json", "[]"), ("anatomy_prob", "0.5\n"), ("orientation", "0.5 30\n"),
                       ("init.pt", "init")):
        (run_dir / name).write_text(text)
    before = listing(run_dir)

    def branch(src, dst):
        return subprocess.run(["bash", str(REPO / "scripts" / "branch_run.sh"), str(src), str(dst)],
                              capture_output=True, text=True, timeout=60)

    new = tmp_path / "branches" / "turned"
    done = branch(run_dir, new)
    assert done.returncode == 0, done.stderr
    assert sorted(str(p.relative_to(new)) for p in new.rglob("*")) == [
        "anatomy_prob", "branched_from", "history.json", "init.pt", "models",
        "models/checkpoint_checkpoint_epoch=12.pt", "orientation"]
    assert (new / "models" / "checkpoint_checkpoint_epoch=12.pt").read_text() == "epoch 12"
    assert (new / "orientation").read_text() == "0.5 30\n"
    assert (new / "branched_from").read_text() == f"{run_dir} epoch 12\n"
    assert listing(run_dir) == before and sorted(p.name for p in new.parent.iterdir()) == ["turned"]
    (new / "history.json").write_text("[1]")
    again = branch(run_dir, new)
    assert again.returncode == 2 and "exists" in again.stderr and (new / "history.json").read_text() == "[1]"
    empty = tmp_path / "empty"
    empty.mkdir()
    none = branch(empty, tmp_path / "other")
    assert none.returncode == 2 and "no checkpoint" in none.stderr and not (tmp_path / "other").exists()


def test_newest_checkpoint_is_the_largest_epoch_not_the_latest_file(tmp_path):
    """``scripts/checkpoints.sh``: epoch 10 is newer than epoch 9 (not by the name's sort order, not by file time);
    a run without checkpoints has epoch 0 and no path."""
    import os
    import subprocess

    models = tmp_path / "run" / "models"
    models.mkdir(parents=True)
    for epoch in (10, 9, 2):  # epoch 9 and 2 written last: the latest file times
        (models / f"checkpoint_checkpoint_epoch={epoch}.pt").write_bytes(b"")
    os.utime(models / "checkpoint_checkpoint_epoch=10.pt", (1_000_000, 1_000_000))
    lib = REPO / "scripts" / "checkpoints.sh"

    def ask(run: Path) -> list[str]:
        out = subprocess.run(["bash", "-c", f'source "{lib}"; newest_epoch "$1"; newest_checkpoint "$1"', "x",
                              str(run)], capture_output=True, text=True, timeout=30)
        assert out.returncode == 0, out.stderr
        return out.stdout.split("\n")[:2]

    assert ask(tmp_path / "run") == ["10", str(models / "checkpoint_checkpoint_epoch=10.pt")]
    assert ask(tmp_path / "empty") == ["0", ""]


def test_the_gpu_script_resumes_only_a_started_run_and_brings_back_its_newest_checkpoint(tmp_path):
    """``scripts/train_context_gpu.sh`` around a stand-in ``train_context_model.sh`` (it records its arguments and
    writes epochs 9 and 10, then stops as the time limit would, exit status 124): a run folder without a checkpoint
    starts without ``--resume``, one with a checkpoint gets ``--resume``; OUT_DIR receives the epoch-10 checkpoint and
    the log; another exit status of the training is the script's own, nothing brought back."""
    import os
    import shutil
    import subprocess

    scripts = tmp_path / "repo" / "scripts"
    scripts.mkdir(parents=True)
    for name in ("train_context_gpu.sh", "checkpoints.sh"):
        shutil.copy(REPO / "scripts" / name, scripts / name)
    (scripts / "train_context_model.sh").write_text(
        '#!/usr/bin/env bash\necho "$@" >> "$1/calls"\nmkdir -p "$1/models"\n'
        'for e in 10 9; do : > "$1/models/checkpoint_checkpoint_epoch=$e.pt"; done\n'
        'echo log > "$1/train_log.txt"\nexit "${STAND_IN_STATUS:-124}"\n')
    (scripts / "train_context_model.sh").chmod(0o755)
    run_dir, out_dir = tmp_path / "run", tmp_path / "out"
    run_dir.mkdir()

    def gpu(**env: str) -> subprocess.CompletedProcess:
        return subprocess.run(["bash", str(scripts / "train_context_gpu.sh"), str(run_dir), str(out_dir)],
                              env={**os.environ, "MINUTES": "1", **env}, capture_output=True, text=True, timeout=60)

    first = gpu()
    assert first.returncode == 0, first.stderr
    assert sorted(p.name for p in (out_dir / "models").iterdir()) == ["checkpoint_checkpoint_epoch=10.pt"]
    assert (out_dir / "train_log.txt").read_text() == "log\n"
    second = gpu()
    assert second.returncode == 0, second.stderr
    calls = (run_dir / "calls").read_text().splitlines()
    assert calls == [f"{run_dir} 100000", f"{run_dir} 100000 --resume"]
    shutil.rmtree(out_dir)
    failed = gpu(STAND_IN_STATUS="3")
    assert failed.returncode == 3 and "exit status 3" in failed.stderr and not out_dir.exists()
