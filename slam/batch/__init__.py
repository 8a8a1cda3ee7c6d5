"""Batches of SLAM runs: many logs × many settings, each run a Ray task (``slam batch``).

* :mod:`slam.batch.spec` — the batch: a spec file (or the command line) expanded into one
  :class:`~slam.batch.spec.Job` per (log, setting), with the content hashes ``--resume`` compares;
* :mod:`slam.batch.executor` — the Ray executor (local instance or ``--address``), shared with
  ``slam loops --parallel``; the only module that imports Ray.

The task itself, the ``slam run`` code path for one job, is :mod:`slam.cli.batch_task`; the tables and
the report are :mod:`evaluation.batch_report`.
"""
