// outputs.ts: PNG bytes are built here chunk by chunk from the PNG specification (length,
// type, data, CRC; the CRC is not checked by the reader, so zeros stand in), and the sentences
// are written out by hand from the job figures.
import assert from "node:assert/strict";
import { describe, test } from "node:test";

import { layerScale, matteText, noiseTargetShortfall, pngText, scaleValue } from "../src/outputs";

function chunk(type: string, data: number[]): number[] {
  const n = data.length;
  return [(n >>> 24) & 255, (n >>> 16) & 255, (n >>> 8) & 255, n & 255, ...[...type].map((c) => c.charCodeAt(0)), ...data, 0, 0, 0, 0];
}
const text = (keyword: string, value: string) => chunk("tEXt", [...`${keyword}\0${value}`].map((c) => c.charCodeAt(0)));
const SIGNATURE = [0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a];
const IHDR = chunk("IHDR", [0, 0, 0, 4, 0, 0, 0, 4, 8, 2, 0, 0, 0]);

describe("pngText", () => {
  test("reads every tEXt chunk before the image data", () => {
    const png = new Uint8Array([
      ...SIGNATURE, ...IHDR, ...chunk("gAMA", [0, 0, 0xb1, 0x8f]),
      ...text("renderfarm:scale_min", "0"), ...text("renderfarm:scale_max", "0.125"),
      ...chunk("IDAT", [1, 2, 3]), ...text("after", "ignored"), ...chunk("IEND", []),
    ]);
    assert.deepEqual(pngText(png), { "renderfarm:scale_min": "0", "renderfarm:scale_max": "0.125" });
  });
  test("not a PNG, or cut short: what was read whole", () => {
    assert.deepEqual(pngText(new Uint8Array([1, 2, 3, 4, 5, 6, 7, 8, 9])), {});
    const whole = [...SIGNATURE, ...text("a", "1")];
    const cut = [...whole, ...text("b", "2")].slice(0, whole.length + 10);
    assert.deepEqual(pngText(new Uint8Array(cut)), { a: "1" });
  });
});

describe("layerScale", () => {
  test("the values of black and white", () => {
    assert.deepEqual(layerScale({ "renderfarm:scale_min": "0", "renderfarm:scale_max": "256.0" }), { min: 0, max: 256 });
  });
  test("none without a scale, or with a malformed or empty one", () => {
    assert.equal(layerScale({}), null);
    assert.equal(layerScale({ "renderfarm:scale_min": "0", "renderfarm:scale_max": "inf" }), null);
    assert.equal(layerScale({ "renderfarm:scale_min": "0", "renderfarm:scale_max": "0" }), null);
  });
});

describe("scaleValue", () => {
  test("error in percent, spp in samples, standard error in 3 digits", () => {
    assert.equal(scaleValue("error", 0.0312), "3.12%");
    assert.equal(scaleValue("error", 0), "0.00%");
    assert.equal(scaleValue("spp", 1024), "1,024");
    assert.equal(scaleValue("spp", 7.5), "7.5");
    assert.equal(scaleValue("variance", 0.04567), "0.0457");
    assert.equal(scaleValue("variance", 0.000123), "1.23e-4");
    assert.equal(scaleValue("variance", 0), "0");
  });
});

describe("noiseTargetShortfall", () => {
  const job = (state: string, threshold: number, error: number | null = 0.031) => ({
    state,
    settings: { noise_threshold: threshold, max_spp: 1024 },
    progress: { tiles_total: 16, error },
  });
  const stops = (converged: number, maxSpp: number, time: number) => [
    ...Array(converged).fill({ reason: "converged" }),
    ...Array(maxSpp).fill({ reason: "max_spp" }),
    ...Array(time).fill({ reason: "time_limit" }),
  ];
  test("says which tiles stopped short and why", () => {
    assert.equal(
      noiseTargetShortfall(job("completed", 0.02), stops(11, 3, 2)),
      "Completed without reaching the noise target of 2.00%: 5 of 16 tiles stopped before it, 3 at max_spp (1,024 spp), 2 at the time limit; image error 3.10%.",
    );
    assert.equal(
      noiseTargetShortfall(job("completed", 0.02, null), stops(0, 0, 10)),
      "Completed without reaching the noise target of 2.00%: 16 of 16 tiles stopped before it, 10 at the time limit, 6 otherwise.",
    );
  });
  test("nothing when every tile converged, when there was no target, or before completion", () => {
    assert.equal(noiseTargetShortfall(job("completed", 0.02), stops(16, 0, 0)), null);
    assert.equal(noiseTargetShortfall(job("completed", 0), stops(0, 16, 0)), null);
    assert.equal(noiseTargetShortfall(job("running", 0.02), stops(3, 1, 0)), null);
    assert.equal(noiseTargetShortfall(job("cancelled", 0.02), stops(3, 1, 0)), null);
  });
});

describe("matteText", () => {
  test("the node covering most of the pixel first, its material and root node", () => {
    const m = {
      objects: [{ name: "wheel", coverage: 0.625 }, { name: "road", coverage: 0.25 }],
      materials: [{ name: "rubber", coverage: 0.625 }],
      assets: [{ name: "car", coverage: 0.625 }],
    };
    assert.equal(matteText(m), "object wheel (63%), road (25%) · material rubber (63%) · asset car (63%)");
  });
  test("a node that is its own root is not named twice; nothing hit", () => {
    const lamp = [{ name: "lamp", coverage: 1 }];
    assert.equal(matteText({ objects: lamp, materials: [], assets: lamp }), "object lamp (100%)");
    assert.equal(matteText({ objects: [], materials: [], assets: [] }), "nothing");
  });
});
