"""Applications over the library: the ``geofeat`` command (`cli`), ``geofeat extract`` (`extract`), the demo data (`demo`) and the command of ``benchmarks/run.py`` (`benchmark`)."""
