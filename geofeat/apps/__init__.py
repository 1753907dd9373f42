"""Applications over the library: the ``geofeat`` command (`cli`), ``geofeat extract`` (`extract`) and the demo data (`demo`)."""
