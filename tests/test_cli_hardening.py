"""The command line with bad or awkward inputs: clean messages, readable output."""

from __future__ import annotations

import json
import math
from dataclasses import fields

import pytest

from diamond_sss.cli.data_commands import format_bounds
from diamond_sss.cli.main import main
from diamond_sss.data.embedded import embedded_dataset
from diamond_sss.training.config import TrainConfig, describe_config, make_config, parse_sets


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
    assert [key for key, _, _ in rows] == [f.name for f in fields(TrainConfig)]
    values = {key: value for key, value, _ in rows}
    assert values["densify_grad_threshold"] == 0.0002 and values["lambda_sil"] == 0.0
    assert describe_config("diamond")[0] == ("iterations", 10_000, "training steps")
    assert all(meaning and not meaning.endswith(".") for _, _, meaning in rows)
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
