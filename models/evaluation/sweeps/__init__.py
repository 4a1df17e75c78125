"""Searches behind the presets and the projection choice (docs/results.md): pure functions (`run(...)`
with keyword arguments) that `cortexloc eval` runs (service/cli/experiments.py).

    sweep.py              grid world search behind `cortexloc-grid`   (cortexloc eval grid-sweep)
    nordland_sweep.py     cross-season search behind `cortexloc-default` (cortexloc eval nordland-sweep)
    projection_parity.py  dense against sparse sLSBH projection AUC   (cortexloc eval projection-parity)
    localiser_sweep.py    the online localiser's defaults and the EfficientNet block, docs/results.md §8
                          (cortexloc eval localiser-sweep)
"""
