"""The command line with bad or awkward inputs: clean messages, readable output."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from diamond_sss.cli.data_commands import format_bounds
from diamond_sss.cli.main import main
from diamond_sss.data.analytic import make_capture
from diamond_sss.data.embedded import embedded_dataset
from diamond_sss.data.images import write_png
from diamond_sss.training.config import FIELDS, FLAT_KEYS
from diamond_sss.training.overrides import describe_config, make_config, parse_sets


def child_environment() -> dict[str, str]:
    """This process's environment with the source tree first on PYTHONPATH (kept: the paths already there)."""
    paths = [str(Path(__file__).parents[1] / "src"), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
    return {**os.environ, "PYTHONPATH": os.pathsep.join(paths)}


def run_child(script: str, env: dict[str, str]) -> subprocess.CompletedProcess:
    """Run a Python script in a child interpreter; a failure shows the child's stderr."""
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, check=False)
    assert result.returncode == 0, result.stderr
    return result


def test_info_prints_bounds_as_text_without_negative_zero(capsys):
    demo = embedded_dataset()
    main(["info", "--data", str(demo)])
    table = capsys.readouterr().out
    assert "-0.0" not in table and "{" not in table and "'center'" not in table
    assert "center (0, 0, 0), radius 1.103, near 2.897, far 5.103" in table
    main(["info", "--data", str(demo), "--json"])
    bounds = json.loads(capsys.readouterr().out)["bounds"]
    assert bounds["center"] == [0.0, 0.0, 0.0] and all(math.copysign(1.0, x) == 1.0 for x in bounds["center"])


def test_format_bounds():
    text = format_bounds({"center": [-0.0, 0.25, -1.5], "radius": 2.0, "near": 0.123456, "far": 10.0})
    assert text == "center (0, 0.25, -1.5), radius 2, near 0.1235, far 10"


@pytest.mark.parametrize("item", ["position_lr_init=inf", "lambda_mask=nan", "lambda_dssim=-inf"])
def test_set_refuses_non_finite_values_naming_the_key(item):
    key = item.split("=")[0]
    with pytest.raises(ValueError, match=f"config key '{key}' must be a finite number"):
        parse_sets([item])


def test_set_refuses_non_finite_integers_and_config_files(tmp_path):
    with pytest.raises(ValueError, match="config key 'iterations' expects int, got 'inf'"):
        parse_sets(["iterations=inf"])
    path = tmp_path / "best.json"
    path.write_text('{"lambda_sil": NaN}')
    with pytest.raises(ValueError, match=r"best\.json: config key 'lambda_sil' must be a finite number"):
        make_config("diamond", config_file=path)


def test_config_lists_every_key_with_its_preset_value_and_meaning(capsys):
    rows = describe_config("sss3dgs")
    assert [key for key, _, _, _ in rows] == list(FIELDS) and len(rows) == 88
    assert [flat for _, flat, _, _ in rows] == list(FLAT_KEYS)
    values = {key: value for key, _, value, _ in rows}
    assert values["densify.grow_grad2d"] == 0.0002 and values["losses.lambda_sil"] == 0.0
    assert describe_config("diamond")[0] == ("schedule.iterations", "iterations", 10_000, "training steps")
    assert ("densify.refine_every", "densification_interval", 100,
            "steps between densifications") in rows
    assert all(meaning and not meaning.endswith(".") for _, _, _, meaning in rows)
    main(["config", "--preset", "sss3dgs", "--json"])
    assert json.loads(capsys.readouterr().out) == values
    main(["config", "--preset", "diamond"])
    table = capsys.readouterr().out
    assert all(key in table for key in values)
    with pytest.raises(SystemExit):
        main(["config", "--preset", "nope"])
    assert "unknown preset 'nope'" in capsys.readouterr().err


def test_set_help_says_repeatable_once_and_where_the_keys_are(capsys):
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    text = " ".join(capsys.readouterr().out.replace("│", " ").split())
    assert text.count("(repeatable)") == 1 and "diamond-sss config" in text


def test_lpips_and_empty_mask_warnings_are_one_line_each_once(tmp_path):
    make_capture(tmp_path, views=2, lights=1, size=8)
    write_png(tmp_path / "train/v000_l000.png", np.zeros((8, 8, 4), np.uint8))
    write_png(tmp_path / "train/v001_l000.png", np.zeros((8, 8, 4), np.uint8))
    script = (
        "from diamond_sss.cli.main import configure_logging\n"
        "from diamond_sss.data import OLATDataset\n"
        "from diamond_sss.losses.lpips import load_lpips\n"
        "configure_logging()\n"
        "load_lpips(None); load_lpips(None)\n"
        f"ds = OLATDataset({str(tmp_path)!r})\n"
        "[ds.load(i) for i in range(len(ds))]\n"
    )
    env = child_environment()
    env.pop("DIAMOND_SSS_LPIPS_WEIGHTS", None)
    result = run_child(script, env)
    lines = result.stderr.splitlines()
    assert len(lines) == 2, result.stderr
    assert lines[0] == "WARNING: LPIPS is disabled: no weights file given and $DIAMOND_SSS_LPIPS_WEIGHTS is not set"
    assert lines[1].startswith("WARNING: ") and "v000_l000.png: the mask is empty (frame 0 of" in lines[1]


def test_cli_help_imports_no_heavy_package():
    script = (
        "import contextlib, io, sys\n"
        "import diamond_sss.cli.main as cli\n"
        "for argv in (['--help'], ['train', '--help'], ['synth', '--help'], ['nvs', '--help'], ['run', '--help'],\n"
        "             ['finetune-nvs', '--help'], ['finetune-relight', '--help']):\n"
        "    try:\n"
        "        with contextlib.redirect_stdout(io.StringIO()):\n"
        "            cli.main(argv)\n"
        "    except SystemExit:\n"
        "        pass\n"
        "heavy = ('torch', 'diffusers', 'transformers', 'mitsuba', 'optuna', 'viser', 'matplotlib')\n"
        "print(','.join(m for m in heavy if m in sys.modules))\n"
    )
    env = child_environment()
    result = run_child(script, env)
    assert result.stdout.strip() == ""
