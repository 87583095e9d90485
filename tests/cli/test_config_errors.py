"""Unknown keys and options on the command line: one line with the closest names, before torch loads."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from shapecorr.cli.config_errors import check_overrides, closest
from shapecorr.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]
CONFIGS = REPO / "configs"


@pytest.mark.parametrize("config, overrides, expected", [
    ("train", ["trainer.max_step=3"], "did you mean trainer.max_steps=3"),
    ("train", ["model=deep_shell"], "did you mean model=deep_shells"),
    ("evaluate", ["+max_pair=2"], "did you mean max_pairs=2"),
    ("evaluate", ["max_pair=2"], "did you mean max_pairs=2"),
    ("train", ["traner.max_steps=3"], "did you mean trainer.max_steps=3"),
    ("evaluate", ["model=descriptor_nn", "model.k_eigg=3"], "model has no 'k_eigg'"),
    ("train", ["modl=deep_shells"], "did you mean model=deep_shells"),
    ("evaluate", ["data=faust", "data.root=/x"], "did you mean data=faust_r"),
    ("train", ["-m", "model=deep_shells,neuromorp"][1:], "did you mean model=neuromorph"),
    ("train", ["+data.synthetic.n_hole=1"], "did you mean +data.synthetic.n_holes=1"),
])
def test_unknown_names_suggest_the_closest(config, overrides, expected):
    with pytest.raises(ConfigError) as err:
        check_overrides(CONFIGS, config, overrides)
    message = str(err.value)
    assert expected in message and "\n" not in message
    assert "+trainer.max_step" not in message and "+max_pair" not in message.split("did you mean")[-1]


@pytest.mark.parametrize("config, overrides", [
    ("train", ["trainer.max_steps=3", "model=neuromorph", "data=synthetic_small"]),
    ("train", ["+callbacks.extra={_target_: pytorch_lightning.callbacks.Timer}"]),   # an open map
    ("train", ["model=deep_shells", "model/backbone=identity"]),
    ("evaluate", ["model=descriptor_nn", "threads=1", "workers=2", "max_pairs=3"]),
    ("prepare", ["+operators.n_eig=300"]),
    ("evaluate", ["model=smooth_shells,descriptor_nn"]),   # a sweep: every value checked
    ("train", ["hydra.run.dir=/tmp/x", "~logger"]),
    ("train", ["+data.synthetic.n_holes=1", "+data.synthetic.test_fraction=0.34"]),   # generator options
    ("evaluate", ["data=faust_r", "data.root=/x", "~data.splits.test", "+data.splits.test={names:[a,b]}"]),
    ("evaluate", ["+model._target_=my_package.MyMatcher"]),   # a matcher of one's own, no model= group option
    ("evaluate", ["ckpt_path=C", "+model.refine=false"]),     # keys on top of the checkpoint's recipe
])
def test_valid_command_lines_pass(config, overrides):
    cfg = check_overrides(CONFIGS, config, overrides)
    assert "paths" in cfg


def test_added_key_accepted_where_the_constructor_takes_it():
    cfg = check_overrides(CONFIGS, "train", ["+trainer.barebones=false"])
    assert cfg.trainer.barebones is False
    with pytest.raises(ConfigError, match="did you mean trainer.max_steps"):
        check_overrides(CONFIGS, "train", ["+trainer.max_step=3"])


def test_closest():
    assert closest("max_pair", ["max_pairs", "pairs", "seed"])[0] == "max_pairs"
    assert closest("zzz", ["max_pairs", "seed"]) == []


def _run(script, *args, env=None):
    return subprocess.run([sys.executable, str(REPO / script), *args], cwd=REPO, capture_output=True, text=True,
                          timeout=120, env={**os.environ, **(env or {})}, check=False)


@pytest.mark.parametrize("script, args, expected", [
    ("train.py", ["trainer.max_step=3"], "did you mean trainer.max_steps=3"),
    ("evaluate.py", ["+max_pair=2", "model=descriptor_nn"], "did you mean max_pairs=2"),
    ("evaluate.py", ["model=descriptor_nn", "data=faust_r"], "SHAPECORR_FAUST_R"),
    ("evaluate.py", ["model=deep_shells_published", "data=folder", f"data.root={REPO / 'configs'}"],
     "SHAPECORR_DEEP_SHELLS_WEIGHTS"),
    # the data group the experiment selects, not the script's default
    ("train.py", ["experiment=deep_shells_faust_r", "data.root=/nonexistent"], "data=faust_r needs a folder"),
])
def test_scripts_stop_with_one_line(script, args, expected):
    proc = _run(script, *args, env={"SHAPECORR_FAUST_R": "", "SHAPECORR_DEEP_SHELLS_WEIGHTS": ""})
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and expected in lines[0]
    if "SHAPECORR" in expected:
        assert "Data and weights" in lines[0]


def test_help_lists_only_the_groups_of_the_script():
    evaluate = _run("evaluate.py", "--help").stdout
    train = _run("train.py", "--help").stdout
    assert "Evaluate a matcher" in evaluate and "  postprocess:" in evaluate and "  trainer:" not in evaluate
    assert "  quick:" not in evaluate and "  loss:" not in evaluate and "threads:" in evaluate
    assert "Train a learned" in train and "  trainer:" in train and "  postprocess:" not in train
    assert "  interpolator:" not in train
