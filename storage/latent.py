"""Where a campaign on a ``[latent]`` case keeps its basis in the store (:mod:`tasks.latent`).

``ROOT/<campaign>/latent-basis/vNNNN/``: ``basis.parquet`` (one row per field value,
``parameter`` and ``cell`` as an ensemble's table labels them, ``mean`` and one float64 column
per mode) and ``basis.json`` (the modes kept, the share of the prior's variance they hold, the
modes the prior had, the ``[latent]`` section, the prior's size and seed, and the coefficients
of the deck's own fields). The rest of the campaign is a calibration campaign's.
"""

LATENT_STEP = "latent-basis"
BASIS_FILE = "basis.parquet"
BASIS_DOC = "basis.json"
