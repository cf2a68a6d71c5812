import torch

# Small torch ops slow down 10-100x when two threads compete for the two CI cores.
torch.set_num_threads(1)
