"""PyTorch side: the TorchRL environment over the JAX kitchens, and the models."""
