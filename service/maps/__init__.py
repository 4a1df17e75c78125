"""The maps: one runtime per map (writer thread, TM, index, store), the registry of a data directory,
the encoder pool, recovery and snapshots at the map level (docs/design/service.md §1, §4, §6).

Domain code: it raises the errors of `service.maps.errors` and answers with the dataclasses of
`service.maps.results`; the HTTP layer (`service.routes`, `service.errors`) turns both into replies.
"""
