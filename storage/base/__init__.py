"""The bottom of the house (docs/architecture.md): what every layer may use and none owns. File helpers
(hashing, atomic writes, directory fsync: durable files are storage's trade), the dtype of SDR index
arrays (what the models compute with and the store decodes to) and the process's resident size. It
imports nothing of ours, and it is no store: the models may use it, never the SQLite modules beside it
(the contracts in pyproject.toml). It sits inside `storage/` because the top level of the repository is
fixed (`models/`, `storage/`, `service/`, ...)."""
