"""``python -m diamond_sss.synth.cli``: the ``diamond-sss synth`` command on its own (scripts use it)."""

from __future__ import annotations

import tyro

from diamond_sss.cli.synth_commands import synth

__all__ = ["synth"]

if __name__ == "__main__":
    tyro.cli(synth)
