"""Searches behind the presets and the projection choice (docs/results.md): each a `python -m` script.

    sweep.py              grid world search behind `cortexloc-grid`
    nordland_sweep.py     cross-season search behind `cortexloc-default`
    projection_parity.py  dense against sparse sLSBH projection AUC
    localiser_sweep.py    the online localiser's defaults and the EfficientNet block (docs/results.md §8)
"""
