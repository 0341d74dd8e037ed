"""Loaded by Python at start-up where this folder is on PYTHONPATH: see ``final_sr_sweep.py``."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from final_sr_sweep import install_from_environment

install_from_environment()
