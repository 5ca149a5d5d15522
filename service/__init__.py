"""The streaming VFM service: Zenoh in, predictions out, an HTTP API, a durable SQLite store.

Public surface: ``service.config.load_settings`` / ``Settings``, ``service.app.Service``,
``serve`` and ``running``, ``service.api.create_app``. See ``service/README_SECTION.md``.
Submodules are imported where used, so that ``vfm --help`` stays fast.
"""
