"""The memory (docs/design/science.md §3, §4): SDR sequences -> winner cells.

    temporal_memory.py  TemporalMemory and StreamContext (the readable interface, state_dict/from_state)
    _tm_kernels.py      numba kernels of one step: step (active and winner cells, learning), activity
    _tm_synapses.py     the synapse arrays' layout, reverse index and primitives (adapt, grow, destroy)
    mcn.py              the MCN baseline
"""
