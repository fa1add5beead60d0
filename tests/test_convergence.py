"""Convergence on real renders (docs/architecture.md, "Statistics"): adaptive stopping,
calibrated errors, and an image that does not depend on how many workers rendered it.

The reference is the Cornell box at 96x96 with 4096 samples per pixel, rendered by the same
farm; its own reported variance is accounted for in every comparison (subtracted from measured
squared errors, added to predicted ones) rather than ignored. Tiles are 24x24: the measured error
of a tile is itself a random quantity, and with 576 pixels it fluctuates by about 3%.
"""

from __future__ import annotations

import numpy as np
import pytest

from renderfarm.cli.localfarm import LocalFarm, spawn_workers, stop_processes
from renderfarm.client import Client
from renderfarm.domain.merge import DARK_FLOOR
from renderfarm.infra.images import read_exr

from .conftest import CORNELL
from .waiting import wait_until

W = H = 96
TILE = 24
LUMA = np.array([0.2126, 0.7152, 0.0722])


def render(client: Client, tmp_path, name: str, **settings) -> tuple[dict, dict]:
    base = {"width": W, "height": H, "tile_size": TILE, "seed": 11}
    job = client.submit(CORNELL, settings={**base, **settings}, name=name)
    job = client.wait(job["id"], poll_s=0.2, timeout_s=900)
    assert job["state"] == "completed", job["error"]
    path = tmp_path / f"{name}.exr"
    path.write_bytes(client.image(job["id"], "exr"))
    return client.get(job["id"]), read_exr(str(path))


def luminance(ch: dict) -> np.ndarray:
    return ch["R"] * LUMA[0] + ch["G"] * LUMA[1] + ch["B"] * LUMA[2]


@pytest.fixture(scope="module")
def reference(farm, tmp_path_factory):
    with Client(farm.url, timeout=60) as client:
        _, ch = render(
            client, tmp_path_factory.mktemp("ref"), "reference", noise_threshold=0, max_spp=4096
        )
    return luminance(ch), ch["variance.Y"].astype(np.float64)


def tile_errors(y: np.ndarray, ref: np.ndarray, ref_var: np.ndarray) -> np.ndarray:
    """Measured relative error of every tile against the reference, defined like the server's
    estimate: RMS over the tile of |Y - Y_ref| / max(Y_ref, DARK_FLOOR), with the reference's
    own variance taken out (E[(Y - Y_ref)^2] = error^2 + Var(Y_ref))."""
    scale = np.maximum(ref, DARK_FLOOR) ** 2
    sq = ((y - ref) ** 2 - ref_var) / scale

    def per_tile(a):
        return a.reshape(H // TILE, TILE, W // TILE, TILE).transpose(0, 2, 1, 3).mean(axis=(2, 3))

    return np.sqrt(np.maximum(per_tile(sq), 0.0)).ravel()


def test_adaptive_stopping_meets_the_threshold_and_halving_it_halves_the_error(
    farm, reference, tmp_path
):
    ref, ref_var = reference
    with Client(farm.url, timeout=60) as client:
        measured = {}
        for threshold in (0.1, 0.05):
            job, ch = render(
                client,
                tmp_path,
                f"adaptive-{threshold}",
                noise_threshold=threshold,
                min_spp=8,
                max_spp=8192,
            )
            stops = job["stops"]
            assert len(stops) == (W // TILE) * (H // TILE)
            converged = [s for s in stops if s["reason"] == "converged"]
            assert len(converged) == len(stops), "every tile should converge before max_spp"
            spps = {s["spp"] for s in converged}
            assert len(spps) > 1, "easy and hard tiles should stop at different spp"
            errors = tile_errors(luminance(ch), ref, ref_var)
            print(f"threshold {threshold}: {np.mean(errors < threshold):.0%} of tiles below it,"
                  f" largest measured error {errors.max():.4f}, spp {sorted(spps)}")  # fmt: skip
            assert np.mean(errors < threshold) >= 0.9, (threshold, errors)
            measured[threshold] = float(np.sqrt(np.mean(errors**2)))
    ratio = measured[0.05] / measured[0.1]
    assert 0.4 <= ratio <= 0.65, measured


def test_per_pixel_adaptive_stops_each_pixel_near_the_threshold(farm, reference, tmp_path):
    """settings.adaptive pixel: every pixel gets at least the ramp's 64 samples and then stops
    on its own error, so the spp layer varies within tiles; the image's measured per-pixel
    relative error is about the threshold (its RMS below it: a pixel stops when the RMS of its
    3x3 neighbourhood's estimates is), where per-tile stopping leaves the noisy pixels of a
    tile far above it; and the variance the EXR reports for a stopped pixel (its own, frozen at
    its stop) still predicts its error."""
    ref, ref_var = reference
    threshold = 0.1
    measured = {}
    with Client(farm.url, timeout=60) as client:
        for adaptive in ("pixel", "tile"):
            job, ch = render(client, tmp_path, f"{adaptive}-{threshold}", adaptive=adaptive,
                             noise_threshold=threshold, min_spp=8, max_spp=8192)  # fmt: skip
            y = luminance(ch)
            scale = np.maximum(ref, DARK_FLOOR) ** 2
            err2 = ((y - ref) ** 2 - ref_var) / scale
            measured[adaptive] = (job, ch, err2)
    job, ch, err2 = measured["pixel"]
    spp = ch["spp"].astype(np.float64)
    assert spp.min() >= 64
    assert job["progress"]["mean_spp"] == pytest.approx(spp.mean(), rel=1e-6)
    tiles = spp.reshape(H // TILE, TILE, W // TILE, TILE).transpose(0, 2, 1, 3)
    varying = [t.max() > 1.5 * t.min() for t in tiles.reshape(-1, TILE, TILE)]
    assert np.mean(varying) >= 0.5, "pixels of a tile should stop at different counts"
    # The hardest pixels: the top tenth by relative noise per sample (the reference's variance
    # of the mean times its 4096 samples, over its brightness).
    noise = np.sqrt(ref_var * 4096) / np.maximum(ref, DARK_FLOOR)
    hard = noise >= np.percentile(noise, 90)
    rms = {k: float(np.sqrt(max(np.mean(v[2]), 0.0))) for k, v in measured.items()}
    rms_hard = {k: float(np.sqrt(max(np.mean(v[2][hard]), 0.0))) for k, v in measured.items()}
    print(f"pixel: RMS {rms['pixel']:.4f}, hardest tenth {rms_hard['pixel']:.4f}, mean spp "
          f"{spp.mean():.0f}; tile: RMS {rms['tile']:.4f}, hardest tenth {rms_hard['tile']:.4f}, "
          f"mean spp {measured['tile'][0]['progress']['mean_spp']:.0f}")  # fmt: skip
    assert rms["pixel"] < threshold
    assert rms_hard["pixel"] < 0.8 * rms_hard["tile"]
    # The variance the EXR reports still predicts the squared error as well as a tile's does
    # (sobol's between-batch estimate is conservative: the ratio is below 1 in both).
    ratio = {}
    for k, (_, ch, _) in measured.items():
        var = ch["variance.Y"].astype(np.float64)
        informative = var > 0
        err = (luminance(ch) - ref)[informative] ** 2
        ratio[k] = float(np.mean(err) / np.mean((var + ref_var)[informative]))
    print(
        f"measured / predicted squared error: pixel {ratio['pixel']:.3f}, tile {ratio['tile']:.3f}"
    )
    assert ratio["pixel"] < 1.0
    assert 0.5 < ratio["pixel"] / ratio["tile"] < 2.0


@pytest.mark.parametrize("sampler", ["independent", "sobol"])
def test_reported_error_is_calibrated(farm, reference, tmp_path, sampler):
    """Independent samples: the reported sigma is the ordinary sample variance over all the
    samples (thousands of degrees of freedom), so about 95% of pixels lie within 2 sigma (a
    little less: path-traced radiance is skewed). Sobol: the between-batch estimate has only
    B - 1 = 20 degrees of freedom at 1024 spp (a Student t: 94.1% within 2 sigma if it were
    exact) but is conservative, since batches of one Owen-scrambled sequence are negatively
    correlated, so at least 95%. (At 256 spp, B - 1 = 8 and t gives only 91.9%.)"""
    ref, ref_var = reference
    with Client(farm.url, timeout=60) as client:
        _, ch = render(client, tmp_path, f"calib-{sampler}", sampler=sampler,
                       noise_threshold=0, max_spp=1024)  # fmt: skip
    y = luminance(ch)
    sigma = np.sqrt(ch["variance.Y"].astype(np.float64) + ref_var)
    informative = sigma > 0  # pixels seeing only the emitter or nothing have no noise at all
    within = np.abs(y - ref)[informative] <= 2 * sigma[informative]
    coverage = float(np.mean(within))
    print(f"{sampler}: {coverage:.3f} of {informative.sum()} pixels within 2 sigma")
    if sampler == "independent":
        assert 0.90 <= coverage <= 0.985, coverage
    else:
        assert coverage >= 0.95, coverage


@pytest.mark.parametrize("adaptive", ["tile", "pixel"])
def test_one_and_three_workers_give_the_same_image_and_spp(tmp_path, adaptive):
    """The same adaptive job on 1 worker, then on 3 (different task interleavings): identical
    RGB (to float32 rounding) and identical stop decisions, per tile and (adaptive pixel) per
    pixel, whose masks the workers render."""
    settings = {"width": 32, "height": 32, "tile_size": 8, "seed": 5, "adaptive": adaptive}
    settings |= {"noise_threshold": 0.1, "min_spp": 4, "max_spp": 2048}
    with LocalFarm(workers=1, data_dir=tmp_path / "farm", threads=1) as farm:
        with Client(farm.url, timeout=60) as client:
            one_job, one = render(client, tmp_path, "one-worker", **settings)
            extra = spawn_workers(2, farm.grpc_address, threads=1, first_index=1)
            try:
                wait_until(lambda: len(client.workers()) == 3, 30, "3 workers connected")
                three_job, three = render(client, tmp_path, "three-workers", **settings)
            finally:
                stop_processes(extra)
    for c in ("R", "G", "B"):
        np.testing.assert_allclose(three[c], one[c], rtol=1e-6, atol=1e-9)
    np.testing.assert_array_equal(three["spp"], one["spp"])
    key = sorted((s["tile"], s["batch"], s["spp"], s["reason"]) for s in one_job["stops"])
    assert key == sorted((s["tile"], s["batch"], s["spp"], s["reason"]) for s in three_job["stops"])
    assert len(set(one["spp"].ravel().tolist())) > 1  # the stops really were adaptive
