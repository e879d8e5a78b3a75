"""``monai-rigidreg serve``: a DICOM registration service for the clinic.

A DICOM Storage SCP (pynetdicom) receives CT and CBCT series, keeps them on disk with an index
(:mod:`~monai_rigidreg.serve.store`), decides which series is a planning CT and which a CBCT and which CT a CBCT is
registered to (:mod:`~monai_rigidreg.serve.rules`), registers each complete CBCT with a model loaded once
(:mod:`~monai_rigidreg.serve.service`, :mod:`~monai_rigidreg.serve._pipeline`) and sends the DICOM Spatial
Registration to the configured destinations (:mod:`~monai_rigidreg.serve.sender`), retrying with backoff.

The configuration is one JSON file (:mod:`~monai_rigidreg.serve.config`); ``docs/serve.md`` describes how to run
it. Nothing here imports torch or MONAI until a registration runs: the command line (:mod:`~monai_rigidreg.serve.cli`)
answers ``--help``, ``status`` and ``trigger`` at once.
"""
