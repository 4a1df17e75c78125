"""Reading a map's rows back (service/maps/runtime/stored.py, docs/design/service.md §1.2): a page holds
each seq once, a joined row as joined, whatever a join commits between the page's two reads."""

from __future__ import annotations

from types import SimpleNamespace

from service.maps.runtime import stored
from storage.mapschema import JoinedRow


def _row(seq: int) -> SimpleNamespace:
    return SimpleNamespace(seq=seq, observation_id=f"o{seq}", stream="robot", label=None, created_at="t",
                           image_sha256="0" * 64, metadata=None)


class RacedStore:
    """Row 3 is read as held, then a join commits and the joined rows' read finds it joined to row 1."""

    def page(self, after_seq: int, limit: int) -> list[SimpleNamespace]:
        return [_row(s) for s in (2, 3, 4, 5) if s > after_seq][:limit]

    def with_thumbnails(self, seqs: object) -> set[int]:
        return set()

    def joined_rows(self, after_seq: int, limit: int) -> list[JoinedRow]:
        return [JoinedRow(seq=3, observation_id="o3", stream="robot", label=None, created_at="t",
                          image_sha256="0" * 64, metadata=None, place_seq=1)][:limit]


def test_a_row_joined_between_the_two_reads_is_listed_once_as_joined():
    got = stored.page(RacedStore(), 0, 3)  # type: ignore[arg-type]
    assert [(o.seq, o.joined_to) for o in got] == [(2, None), (3, 1), (4, None)]
