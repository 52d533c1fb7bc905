"""A tile joined from parts made apart (:mod:`calib.io.tileparts`)
holds what laspy's own writer would write from the same records, and readers find its chunks."""

from __future__ import annotations

import laspy
import numpy as np
import pytest

from calib.core import frames
from calib.io import lastile
from calib.io.laz import SCALE_M, LasOutputError, OutputCrs
from calib.io.tileparts import LAZ_CHUNK_POINTS, PartError, load_part, make_part, save_part, write_tile

CRS = OutputCrs("LGF", "", (SCALE_M,) * 3, (100.0, 200.0, 0.0), frames.LocalFrame(45.5, -73.5), None)
FIRST_T_GPS_S = 1.3e9
#: part sizes around the chunk size: one point, a chunk and one more, several chunks
SIZES = (1, LAZ_CHUNK_POINTS, LAZ_CHUNK_POINTS + 1, 2 * LAZ_CHUNK_POINTS + 17)


def records(n: int, seed: int, pass_id: int) -> np.ndarray:
    """``n`` tile records of a wiggly line (time order), every field set."""
    rng = np.random.default_rng(seed)
    rec = np.zeros(n, lastile.record_dtype())
    rec["X"] = np.cumsum(rng.integers(-30, 60, n)) + seed * 10_000
    rec["Y"] = rng.integers(-50_000, 50_000, n)
    rec["Z"] = rng.integers(-20_000, 90_000, n)
    rec["gps_time"] = FIRST_T_GPS_S - 1e9 + seed + np.arange(n) * 1e-6
    rec["intensity"] = rng.integers(0, 65_535, n)
    rec["bit_fields"] = 0x11
    rec["scan_angle"] = rng.integers(-15_000, 15_000, n)
    rec["pass_id"] = pass_id
    rec["point_source_id"] = pass_id
    rec["sigma_h_m"] = rng.uniform(0.005, 0.08, n)
    rec["sigma_v_m"] = rng.uniform(0.005, 0.08, n)
    return rec


def written_by_laspy(path, parts: list[np.ndarray]):
    """The tile laspy's writer makes from the records (the way tiles were written before)."""
    header = lastile.tile_header(CRS, 0, "test", {"k": 1}, lastile.survey_date(FIRST_T_GPS_S))
    with laspy.open(path, mode="w", header=header, do_compress=path.suffix == ".laz") as w:
        for p in parts:
            w.write_points(laspy.PackedPointRecord(p, w.header.point_format))


@pytest.mark.parametrize("suffix", [".laz", ".las"])
def test_a_tile_of_parts_holds_what_laspy_writes_from_the_same_records(tmp_path, suffix):
    recs = [records(n, k, pass_id=k % 2 + 3) for k, n in enumerate(SIZES)]
    parts = []
    for k, r in enumerate(recs):
        save_part(tmp_path / f"c{k}.part", make_part(r, compress=suffix == ".laz"))
        parts.append(load_part(tmp_path / f"c{k}.part", r.dtype))
    ours = tmp_path / f"ours{suffix}"
    summary = write_tile(ours, parts, CRS, "test", {"k": 1}, FIRST_T_GPS_S)
    theirs = tmp_path / f"theirs{suffix}"
    written_by_laspy(theirs, recs)
    a, b = laspy.read(ours), laspy.read(theirs)
    assert np.array_equal(a.points.array, np.concatenate(recs))
    assert np.array_equal(b.points.array, np.concatenate(recs))
    for field in ("mins", "maxs", "scales", "offsets", "number_of_points_by_return"):
        assert np.array_equal(getattr(a.header, field), getattr(b.header, field)), field
    for field in ("point_count", "creation_date", "version", "offset_to_point_data", "system_identifier"):
        assert getattr(a.header, field) == getattr(b.header, field), field
    assert [(v.user_id, v.record_id) for v in a.header.vlrs] == [
        (v.user_id, v.record_id) for v in b.header.vlrs
    ]
    assert a.header.file_source_id == 0  # two lines in the tile
    assert summary.n_points == sum(SIZES) and summary.passes == [3, 4]
    assert summary.t_first_gps_s == pytest.approx(FIRST_T_GPS_S, abs=1e-6)
    assert summary.bbox[:3] == tuple(round(float(v), 4) for v in a.header.mins)


def test_the_extra_bytes_bounds_are_the_true_least_and_greatest(tmp_path):
    """laspy's writer records an extra-bytes dimension's bounds from the first point of each batch
    it is given; the joined tile records those of every point."""
    recs = [records(n, k, pass_id=7) for k, n in enumerate((500, 700))]
    path = tmp_path / "t.laz"
    write_tile(path, [make_part(r, True) for r in recs], CRS, "test", {}, FIRST_T_GPS_S)
    eb = laspy.read(path).header.vlrs.get("ExtraBytesVlr")[0]
    every = np.concatenate(recs)
    for s in eb.extra_bytes_structs:
        lo = np.frombuffer(s._min, s._long_type())[0]
        hi = np.frombuffer(s._max, s._long_type())[0]
        name = s.format_name()
        assert (lo, hi) == (every[name].min(), every[name].max()), name


def test_the_chunk_table_names_every_part_s_chunks_and_readers_decode_them(tmp_path):
    """Variable chunks (a part's last chunk is short): the table after the points names each, and
    the readers that decode chunk by chunk (laspy's parallel lazrs reader, which splits the points
    by the table; its chunked iteration) give back every record. (Seeking into such a file is
    not among them: lazrs 0.8.2's seek assumes chunks of one size.)"""
    import io

    import lazrs

    from calib.io.tileparts import laz_vlr

    parts = [
        make_part(records(n, k, 5), True)
        for k, n in enumerate((LAZ_CHUNK_POINTS + 3, 9, 2 * LAZ_CHUNK_POINTS))
    ]
    every = np.concatenate(
        [records(n, k, 5) for k, n in enumerate((LAZ_CHUNK_POINTS + 3, 9, 2 * LAZ_CHUNK_POINTS))]
    )
    path = tmp_path / "t.laz"
    write_tile(path, parts, CRS, "test", {}, FIRST_T_GPS_S)
    raw = io.BytesIO(path.read_bytes())
    raw.seek(laspy.read(path).header.offset_to_point_data)
    table = lazrs.read_chunk_table(raw, laz_vlr())
    assert [tuple(e) for e in table] == [c for p in parts for c in p.laz_chunks or ()]
    assert [n for n, _ in table] == [LAZ_CHUNK_POINTS, 3, 9, LAZ_CHUNK_POINTS, LAZ_CHUNK_POINTS]
    for backend in (laspy.LazBackend.LazrsParallel, laspy.LazBackend.Lazrs):
        with laspy.open(path, laz_backend=backend) as reader:
            got = np.concatenate([c.array for c in reader.chunk_iterator(7_000)])
        assert np.array_equal(got, every), backend


def test_a_torn_or_foreign_part_is_refused_by_name(tmp_path):
    path = tmp_path / "c1.part"
    size = save_part(path, make_part(records(1000, 1, 2), True))
    whole = path.read_bytes()
    assert len(whole) == size
    path.write_bytes(whole[:-10])
    with pytest.raises(PartError, match=f"{path}.*a whole part has {size}"):
        load_part(path, lastile.record_dtype())
    path.write_bytes(whole[:20])
    with pytest.raises(PartError, match=f"{path}: a torn or foreign part"):
        load_part(path, lastile.record_dtype())
    path.write_bytes(b"\0" * size)
    with pytest.raises(PartError, match=f"{path}: not a tile part"):
        load_part(path, lastile.record_dtype())


def test_parts_must_match_the_tile_kind(tmp_path):
    part = make_part(records(10, 1, 2), compress=False)
    with pytest.raises(LasOutputError, match="must be LAZ chunks"):
        write_tile(tmp_path / "t.laz", [part], CRS, "test", {}, FIRST_T_GPS_S)
    with pytest.raises(LasOutputError, match="without points"):
        write_tile(tmp_path / "t.las", [], CRS, "test", {}, FIRST_T_GPS_S)
    assert not list(tmp_path.iterdir())
