"""The streaming VFM service: Zenoh in, predictions out, an HTTP API, a durable SQLite store.

Layout (one job per module):

* ``config``: the settings tree; ``errors``: the domain errors (one hierarchy);
  ``inputs``: checking payloads and keys, counting rejections; ``store``: SQLite with
  typed rows and write operations; ``learning``: building learners, the history fit;
  ``transport``: the bus interface, Zenoh and in-memory;
* ``engine``: the core, free of Zenoh and HTTP (a package: recovery, intake, worker,
  pairing, learning, checkpoints, model_change, fairqueue (one queue per well, served in
  turn), registry (new and retired wells), behind the ``Engine`` facade);
* ``http``: the FastAPI app, a router per concern (a package);
* ``app``: ``Service`` (store + engine + transport), ``serve`` and ``running``;
  ``cli``: ``vfm serve`` and ``vfm export``; ``export``: a store's history in the
  observation format, read-only; ``testing``: loopback settings and ``vfm serve`` in a
  subprocess.

Imports run one way (``app`` -> ``http`` -> ``engine`` -> ``store``/``inputs``/``config``
-> ``vfm_core``). Submodules are imported where used, so that ``vfm --help`` stays fast.
"""
