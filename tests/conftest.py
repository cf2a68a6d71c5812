import sys
from pathlib import Path

import torch

# Small torch ops slow down 10-100x when two threads compete for the two CI cores.
torch.set_num_threads(1)

# The measuring tools the tests use too (`op_audit`) live with the benchmarks, outside the library's packages;
# searched last, so that the tests' own helper modules come first.
sys.path.append(str(Path(__file__).resolve().parents[1] / "benchmarks"))
