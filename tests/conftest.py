"""Test configuration: offline hubs, a private extensions cache, the test helpers on the path."""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
os.environ.setdefault("TORCH_EXTENSIONS_DIR", tempfile.mkdtemp(prefix="diamond_sss_ext_"))
sys.path.insert(0, str(Path(__file__).parent))

import torch

# Small kernels: one thread is as fast on an idle machine and 10x faster on a loaded one.
torch.set_num_threads(1)
