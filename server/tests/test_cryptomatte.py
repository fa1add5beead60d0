"""Cryptomatte's IDs, ranking merge and names (domain/cryptomatte.py, #40), against the
specification's published values and a plain-Python reference of the ranking filter."""

from __future__ import annotations

import json

import numpy as np

from renderfarm.domain import cryptomatte
from renderfarm.domain.cryptomatte import RANKS, Names, merge_ranked, regroup


def test_ids_are_the_specifications_murmurhash3_of_the_name():
    # The specification's manifest example (Cryptomatte 1.1.0, "Manifest").
    assert f"{cryptomatte.hash_bits('bunny'):08x}" == "13851a76"
    assert f"{cryptomatte.hash_bits('default'):08x}" == "42c9679f"
    assert f"{cryptomatte.hash_bits('bunny_porcelain_mat'):08x}" == "b24b26d4"


def test_an_id_is_never_zero_denormal_inf_or_nan():
    """Names whose raw hash has the exponent 0 or 255 get it clamped to 1 or 254 (the
    specification's conversion), so the float is finite and normal."""
    import mmh3

    clamped = {0: None, 255: None}
    for i in range(200_000):
        name = f"n{i}"
        exponent = (mmh3.hash(name, 0, signed=False) >> 23) & 255
        if exponent in clamped and clamped[exponent] is None:
            clamped[exponent] = name
        if all(clamped.values()):
            break
    assert all(clamped.values()), clamped
    for raw, name in clamped.items():
        value = np.float32(cryptomatte.hash_float(name))
        assert np.isfinite(value) and abs(value) >= np.finfo(np.float32).tiny, (raw, name)
        bits = cryptomatte.hash_bits(name)
        assert (bits >> 23) & 255 == (1 if raw == 0 else 254)
        # Only the exponent changed.
        assert bits & 0x807FFFFF == mmh3.hash(name, 0, signed=False) & 0x807FFFFF


def _reference_merge(batches: list[np.ndarray]) -> list[list[tuple[int, int]]]:
    """The ranking filter per pixel in plain Python: each batch's counts added to the pixel's
    dict, then the RANKS largest kept (ties: the smaller label), batch after batch."""
    pixels = batches[0].shape[0]
    kept: list[dict[int, int]] = [{} for _ in range(pixels)]
    for batch in batches:
        for p in range(pixels):
            for r in range(RANKS):
                label, count = int(batch[p, 2 * r]), int(batch[p, 2 * r + 1])
                if label:
                    kept[p][label] = kept[p].get(label, 0) + count
            top = sorted(kept[p].items(), key=lambda kv: (-kv[1], kv[0]))[:RANKS]
            kept[p] = dict(top)
    return [sorted(k.items(), key=lambda kv: (-kv[1], kv[0])) for k in kept]


def _batch(rng, pixels: int, labels: int) -> np.ndarray:
    out = np.zeros((pixels, 2 * RANKS), np.uint32)
    for p in range(pixels):
        chosen = rng.choice(np.arange(1, labels + 1), rng.integers(0, min(labels, RANKS) + 1),
                            replace=False)  # fmt: skip
        pairs = sorted(((int(rng.integers(1, 20)), int(k)) for k in chosen),
                       key=lambda c: (-c[0], c[1]))  # fmt: skip
        for r, (count, label) in enumerate(pairs):
            out[p, 2 * r : 2 * r + 2] = (label, count)
    return out


def test_merging_adds_equal_labels_and_keeps_the_largest_like_the_reference():
    rng = np.random.default_rng(3)
    pixels = 300
    batches = [_batch(rng, pixels, labels=9) for _ in range(6)]  # 9 labels: some are dropped
    stored = np.zeros((pixels, 2 * RANKS), np.uint32)
    for batch in batches:
        stored = merge_ranked(stored, batch)
    want = _reference_merge(batches)
    for p in range(pixels):
        got = [(int(stored[p, 2 * r]), int(stored[p, 2 * r + 1])) for r in range(RANKS)]
        assert [g for g in got if g[0]] == want[p], p
        assert all(g == (0, 0) for g in got[len(want[p]) :])
    # Not vacuous: labels met in several batches were summed, and some pixels dropped labels.
    assert stored[:, 1].max() > 19
    seen = [set().union(*({*b[p, 0::2].tolist()} for b in batches)) - {0} for p in range(pixels)]
    assert max(len(s) for s in seen) > RANKS


def test_merging_is_a_function_of_the_batches_in_order():
    """Two servers merging the same batches in the same order keep the same bits (ties of
    count are broken by label, never by arrival within a batch)."""
    rng = np.random.default_rng(8)
    batches = [_batch(rng, 50, labels=4) for _ in range(4)]
    a = b = np.zeros((50, 2 * RANKS), np.uint32)
    for batch in batches:
        a = merge_ranked(a, batch)
        shuffled = batch.reshape(50, RANKS, 2)[:, ::-1].reshape(50, -1)  # another slot order
        b = merge_ranked(b, np.ascontiguousarray(shuffled))
    assert a.tobytes() == b.tobytes()


def test_assets_sum_the_counts_of_nodes_under_one_root():
    document = {
        "nodes": [{"name": "car", "children": [1, 2]}, {"name": "wheel", "children": [3]},
                  {"name": "door"}, {"name": "bolt"}, {"name": "lamp"}],
    }  # fmt: skip
    names = Names.of(document)
    assert names.roots.tolist() == [0, 1, 1, 1, 1, 5]  # labels: node + 1
    pairs = np.zeros((1, 2 * RANKS), np.uint32)
    pairs[0, :8] = [5, 9, 2, 4, 3, 3, 4, 1]  # lamp 9, wheel 4, door 3, bolt 1
    grouped = regroup(pairs, names.roots)
    assert grouped[0, :4].tolist() == [5, 9, 1, 8]  # lamp 9 ranks before car 8
    assert not grouped[0, 4:].any()
    assert names.label_names("CryptoAsset") == {1: "car", 5: "lamp"}


def test_names_fall_back_to_the_gltf_path_and_the_header_carries_the_manifest():
    names = Names.of({"nodes": [{}, {"name": "b"}], "materials": [{"name": "m"}, {}]})
    assert names.label_names("CryptoObject") == {1: "nodes[0]", 2: "b"}
    assert names.label_names("CryptoMaterial") == {
        1: "m", 2: "materials[1]", cryptomatte.DEFAULT_MATERIAL_LABEL: "default material",
    }  # fmt: skip
    header = names.header("CryptoMaterial")
    key = cryptomatte.metadata_key("CryptoMaterial")
    assert header[f"cryptomatte/{key}/name"] == "CryptoMaterial"
    assert header[f"cryptomatte/{key}/hash"] == "MurmurHash3_32"
    assert header[f"cryptomatte/{key}/conversion"] == "uint32_to_float32"
    manifest = json.loads(header[f"cryptomatte/{key}/manifest"])
    assert set(manifest) == {"m", "materials[1]", "default material"}
    assert manifest["m"] == f"{cryptomatte.hash_bits('m'):08x}"


def test_exr_values_are_ids_and_coverage_per_rank():
    names = Names.of({"nodes": [{"name": "a"}, {"name": "b"}]})
    pairs = np.zeros((1, 1, 2 * RANKS), np.uint32)
    pairs[0, 0, :4] = [2, 6, 1, 2]  # b on 6 samples, a on 2, of 10
    values = cryptomatte.exr_values(pairs, 10, names.id_table("CryptoObject"))
    assert values.dtype == np.float32
    assert values[0, 0, 0] == np.float32(cryptomatte.hash_float("b"))
    assert values[0, 0, 1] == np.float32(0.6)
    assert values[0, 0, 2] == np.float32(cryptomatte.hash_float("a"))
    assert values[0, 0, 3] == np.float32(0.2)
    assert not values[0, 0, 4:].any()
