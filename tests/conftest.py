"""Shared test set-up: one torch thread, as the `vfm` command and the service use.

The VFM's tensors are small; on a machine shared with other work a second thread's
barriers make tests many times slower (see vfm_core.cli._torch_threads)."""

import torch

torch.set_num_threads(1)
