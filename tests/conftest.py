"""Shared test set-up: one torch thread, as the `vfm` command and the service use.

The VFM's tensors are small; on a machine shared with other work a second thread's
barriers make tests many times slower; and glibc's malloc set to keep freed memory for the
next step (see vfm_core.runtime)."""

from vfm_core.runtime import configure

configure(1)
