"""The command line with bad or awkward inputs: clean messages, readable output."""

from __future__ import annotations

import json
import math

from diamond_sss.cli.data_commands import format_bounds
from diamond_sss.cli.main import main
from diamond_sss.data.embedded import embedded_dataset


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
