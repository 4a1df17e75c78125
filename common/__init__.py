"""What every layer may use and none owns (docs/architecture.md): file helpers (hashing, atomic writes,
directory fsync), the dtype of SDR index arrays and the process's resident size. It imports nothing of
ours."""
