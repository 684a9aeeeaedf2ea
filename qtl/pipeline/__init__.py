"""The sweep pipeline's commands: run a paper experiment, evaluate its final policies, measure task compliance.

``qtl-experiment`` (:mod:`~qtl.pipeline.experiment`) runs an experiment's source sweep, then its target sweep, then
writes the report; ``qtl-evaluate`` (:mod:`~qtl.pipeline.evaluate`) tries every run's final policy from common start
states and writes ``final_policies.json``, which ``qtl-report`` reads back (Tables F1-F2); ``qtl-compliance``
(:mod:`~qtl.pipeline.compliance`) measures Λ (Eq. 14) of finished target runs against a source run. Each is also
``python -m qtl.pipeline.<name>``; bad input stops each in one line before any work.
"""
