"""The memory (docs/design/science.md §3, §5): SDR sequences -> winner cells.

    temporal_memory.py  TemporalMemory and StreamContext (the readable interface, state_dict/from_state)
    _tm_kernels.py      numba kernels of one step: active and winner cells, learning
    _tm_activity.py     numba kernels around it: dendrite activity, reverse index, compaction
    mcn.py              the MCN baseline
"""
