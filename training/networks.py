"""Actor network shared by training and export: an MLP (two hidden layers of 64, ReLU) with a tanh output.

The exporter (``firmware_export.onnx_export``) and the C generator rely on exactly this structure:
``net.0`` Linear(obs_dim, h1), ReLU, ``net.2`` Linear(h1, h2), ReLU, ``net.4`` Linear(h2, act_dim), Tanh.
"""
from __future__ import annotations

import torch
from torch import nn


class Actor(nn.Module):
    def __init__(self, obs_dim: int, act_dim: int = 2, hidden: tuple[int, ...] = (64, 64)) -> None:
        super().__init__()
        self.obs_dim = obs_dim
        self.act_dim = act_dim
        self.hidden = tuple(hidden)
        layers: list[nn.Module] = []
        width = obs_dim
        for h in hidden:
            layers += [nn.Linear(width, h), nn.ReLU()]
            width = h
        layers += [nn.Linear(width, act_dim), nn.Tanh()]
        self.net = nn.Sequential(*layers)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.net(obs)
