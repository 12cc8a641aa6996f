"""What uses the searches: ``fj.profile`` (``profile.py``) and batches over several processes
(``distributed.py``). Above ``search`` and ``control`` in the dependency order; ``runtime`` below them holds what
the searches use."""
