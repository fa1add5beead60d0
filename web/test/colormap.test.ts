// colormap.ts. Exposure tables are checked against the sRGB transfer functions written out here
// from IEC 61966-2-1; colour tables against matplotlib's published 256-entry data
// (lib/matplotlib/_cm_listed.py, _inferno_data and _viridis_data) at the indices given.
import assert from "node:assert/strict";
import { describe, test } from "node:test";

import { applyColourMap, applyExposure, colourTable, cssGradient, exposureTable, type ColourMap } from "../src/colormap";

// IEC 61966-2-1: decoding V' -> L and encoding L -> V', both on [0, 1].
function srgbDecode(v: number): number {
  return v <= 0.04045 ? v / 12.92 : ((v + 0.055) / 1.055) ** 2.4;
}
function srgbEncode(l: number): number {
  return l <= 0.0031308 ? 12.92 * l : 1.055 * l ** (1 / 2.4) - 0.055;
}

describe("exposureTable", () => {
  test("has one entry per 8-bit code value", () => {
    assert.equal(exposureTable(0).length, 256);
  });
  test("zero stops is the identity", () => {
    const table = exposureTable(0);
    for (let v = 0; v < 256; v++) assert.equal(table[v], v, `code ${v}`);
  });
  test("matches decode, scale by 2^stops, clamp to 1, encode", () => {
    for (const stops of [-3, -1, -0.5, 0.5, 1, 2.5]) {
      const table = exposureTable(stops);
      for (let v = 0; v < 256; v++) {
        const expected = Math.round(srgbEncode(Math.min(1, srgbDecode(v / 255) * 2 ** stops)) * 255);
        assert.equal(table[v], expected, `${stops} stops, code ${v}`);
      }
    }
  });
  test("one stop down takes white to 188, the sRGB code of half the linear radiance", () => {
    assert.equal(exposureTable(-1)[255], 188);
  });
  test("in the linear toe of the curve one stop halves the code value", () => {
    const table = exposureTable(-1);
    for (const v of [2, 4, 6, 8, 10]) assert.equal(table[v], v / 2, `code ${v}`);
    assert.equal(exposureTable(1)[4], 8);
  });
  test("raising the exposure clips highlights at 255; black stays black", () => {
    const table = exposureTable(2);
    assert.equal(table[0], 0);
    assert.equal(table[255], 255);
    // Linear 1/4 (code 137 decodes to 0.2502) times four is past white.
    assert.equal(table[137], 255);
    assert.ok(table[100] < 255);
  });
  test("is monotonic", () => {
    for (const stops of [-4, -1, 1, 4]) {
      const table = exposureTable(stops);
      for (let v = 1; v < 256; v++) assert.ok(table[v] >= table[v - 1], `${stops} stops, code ${v}`);
    }
  });
});

type Rgb = [number, number, number];

// Rows of matplotlib's tables, by index. The indices 0, 28, ..., 255 are the ten colours
// matplotlib gives for ten evenly spaced values (cmap(np.linspace(0, 1, 10))).
const MATPLOTLIB: Record<ColourMap, Record<number, Rgb>> = {
  inferno: {
    0: [0.001462, 0.000466, 0.013866],
    28: [0.104551, 0.047008, 0.25343],
    56: [0.290763, 0.045644, 0.418637],
    85: [0.472328, 0.110547, 0.428334],
    113: [0.64626, 0.173914, 0.378359],
    127: [0.729909, 0.212759, 0.333861],
    128: [0.735683, 0.215906, 0.330245],
    142: [0.812239, 0.266786, 0.274661],
    170: [0.929644, 0.411479, 0.145367],
    199: [0.985315, 0.608422, 0.024202],
    227: [0.969783, 0.820825, 0.238686],
    255: [0.988362, 0.998364, 0.644924],
  },
  viridis: {
    0: [0.267004, 0.004874, 0.329415],
    28: [0.281412, 0.155834, 0.469201],
    56: [0.244972, 0.287675, 0.53726],
    85: [0.190631, 0.407061, 0.556089],
    113: [0.147607, 0.511733, 0.557049],
    127: [0.128729, 0.563265, 0.551229],
    128: [0.127568, 0.566949, 0.550556],
    142: [0.119699, 0.61849, 0.536347],
    170: [0.20803, 0.718701, 0.472873],
    199: [0.430983, 0.808473, 0.346476],
    227: [0.709898, 0.868751, 0.169257],
    255: [0.993248, 0.906157, 0.143936],
  },
};
const TEN = [0, 28, 56, 85, 113, 142, 170, 199, 227, 255];
const MAPS: ColourMap[] = ["inferno", "viridis"];

const to8bit = (rgb: Rgb): Rgb => rgb.map((c) => Math.round(c * 255)) as Rgb;
const entry = (table: Uint8ClampedArray, i: number): Rgb => [table[i * 3], table[i * 3 + 1], table[i * 3 + 2]];
const hex = (rgb: Rgb) => "#" + rgb.map((c) => c.toString(16).padStart(2, "0")).join("");

describe("colourTable", () => {
  for (const name of MAPS) {
    test(`${name}: 256 RGB triples`, () => {
      assert.equal(colourTable(name).length, 768);
    });
    test(`${name}: its ends are matplotlib's`, () => {
      const table = colourTable(name);
      assert.deepEqual(entry(table, 0), to8bit(MATPLOTLIB[name][0]));
      assert.deepEqual(entry(table, 255), to8bit(MATPLOTLIB[name][255]));
    });
    test(`${name}: entries 85 and 170, which fall on its stops, are matplotlib's`, () => {
      const table = colourTable(name);
      assert.deepEqual(entry(table, 85), to8bit(MATPLOTLIB[name][85]));
      assert.deepEqual(entry(table, 170), to8bit(MATPLOTLIB[name][170]));
    });
    test(`${name}: the middle entries are within 3 levels of matplotlib's`, () => {
      // Between stops the table is a straight line through a curve, so not exact.
      const table = colourTable(name);
      for (const i of [127, 128]) {
        const actual = entry(table, i);
        const expected = MATPLOTLIB[name][i].map((c) => c * 255);
        for (let c = 0; c < 3; c++) {
          assert.ok(Math.abs(actual[c] - expected[c]) <= 3, `${name}[${i}] channel ${c}: ${actual[c]} vs ${expected[c]}`);
        }
      }
    });
  }
  for (const name of MAPS) {
    test(`${name}: every entry is the straight-line mix of the two stops around it, to the nearest level`, () => {
      const stops = TEN.map((i) => to8bit(MATPLOTLIB[name][i]));
      const table = colourTable(name);
      for (let i = 0; i < 256; i++) {
        const x = (i * 9) / 255; // 0 at the first stop, 9 at the last
        const k = Math.min(8, Math.floor(x));
        const f = x - k;
        const expected = [0, 1, 2].map((c) => Math.round(stops[k][c] + (stops[k + 1][c] - stops[k][c]) * f));
        assert.deepEqual(entry(table, i), expected, `${name}[${i}]`);
      }
    });
  }
  test("the two maps are different tables", () => {
    assert.notDeepEqual(entry(colourTable("inferno"), 128), entry(colourTable("viridis"), 128));
  });
});

describe("cssGradient", () => {
  for (const name of MAPS) {
    test(`${name}: left to right through matplotlib's ten evenly spaced colours`, () => {
      const colours = TEN.map((i) => hex(to8bit(MATPLOTLIB[name][i])));
      assert.equal(cssGradient(name), `linear-gradient(to right, ${colours.join(", ")})`);
    });
  }
});

// The DOM's ImageData, for Node: RGBA bytes, row by row.
class FakeImageData {
  readonly data: Uint8ClampedArray;
  constructor(
    readonly width: number,
    readonly height: number,
  ) {
    this.data = new Uint8ClampedArray(width * height * 4);
  }
}
(globalThis as { ImageData?: unknown }).ImageData = FakeImageData;

function image(pixels: number[][]): ImageData {
  const img = new FakeImageData(pixels.length, 1);
  pixels.forEach((p, i) => img.data.set(p, i * 4));
  return img as unknown as ImageData;
}

describe("applyExposure", () => {
  test("maps each colour channel through the exposure table and makes the result opaque", () => {
    const src = image([
      [255, 10, 0, 17],
      [4, 255, 8, 200],
    ]);
    const out = applyExposure(src, -1);
    assert.equal(out.width, 2);
    assert.equal(out.height, 1);
    assert.deepEqual([...out.data], [188, 5, 0, 255, 2, 188, 4, 255]);
    assert.deepEqual([...src.data], [255, 10, 0, 17, 4, 255, 8, 200], "the source is left alone");
  });
});

describe("applyColourMap", () => {
  test("colours each pixel by its red channel and makes the result opaque", () => {
    const src = image([
      [0, 255, 255, 0],
      [255, 0, 0, 0],
      [85, 1, 2, 3],
    ]);
    const out = applyColourMap(src, "viridis");
    const v = MATPLOTLIB.viridis;
    assert.deepEqual([...out.data], [...to8bit(v[0]), 255, ...to8bit(v[255]), 255, ...to8bit(v[85]), 255]);
  });
});
