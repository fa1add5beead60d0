// Pixel transforms of the preview: exposure of the sRGB image and false colour for the
// grayscale layers (error, spp, variance), which the server normalises to their maximum.

export type Rgb = [number, number, number];

function hex(c: string): Rgb {
  return [parseInt(c.slice(1, 3), 16), parseInt(c.slice(3, 5), 16), parseInt(c.slice(5, 7), 16)];
}

// Ten evenly spaced samples of matplotlib's perceptually uniform colour maps (public domain,
// van der Walt and Smith), interpolated linearly into 256-entry tables.
const STOPS = {
  inferno: ["#000004", "#1b0c41", "#4a0c6b", "#781c6d", "#a52c60", "#cf4446", "#ed6925", "#fb9b06", "#f7d13d", "#fcffa4"],
  viridis: ["#440154", "#482878", "#3e4989", "#31688e", "#26828e", "#1f9e89", "#35b779", "#6ece58", "#b5de2b", "#fde725"],
};
export type ColourMap = keyof typeof STOPS;

const tables = new Map<ColourMap, Uint8ClampedArray>();

/** 256 RGB triples (768 bytes) of a colour map. */
export function colourTable(name: ColourMap): Uint8ClampedArray {
  let table = tables.get(name);
  if (table) return table;
  const stops = STOPS[name].map(hex);
  table = new Uint8ClampedArray(256 * 3);
  for (let i = 0; i < 256; i++) {
    const x = (i / 255) * (stops.length - 1);
    const k = Math.min(stops.length - 2, Math.floor(x));
    const f = x - k;
    for (let c = 0; c < 3; c++) table[i * 3 + c] = Math.round(stops[k][c] * (1 - f) + stops[k + 1][c] * f);
  }
  tables.set(name, table);
  return table;
}

/** CSS linear-gradient of a colour map, for legends. */
export function cssGradient(name: ColourMap): string {
  return `linear-gradient(to right, ${STOPS[name].join(", ")})`;
}

const srgbToLinear = (v: number) => (v <= 0.04045 ? v / 12.92 : Math.pow((v + 0.055) / 1.055, 2.4));
const linearToSrgb = (v: number) => (v <= 0.0031308 ? 12.92 * v : 1.055 * Math.pow(v, 1 / 2.4) - 0.055);

/**
 * The 8-bit table of an exposure change of `stops` on sRGB-encoded values: decode to linear
 * radiance, scale by 2^stops, clamp, re-encode. The PNG is clamped to [0, 1] by the server, so
 * lowering the exposure cannot recover highlights (the EXR download keeps them).
 */
export function exposureTable(stops: number): Uint8ClampedArray {
  const table = new Uint8ClampedArray(256);
  const gain = Math.pow(2, stops);
  for (let v = 0; v < 256; v++) {
    const linear = Math.min(1, srgbToLinear(v / 255) * gain);
    table[v] = Math.round(linearToSrgb(linear) * 255);
  }
  return table;
}

export function applyExposure(src: ImageData, stops: number): ImageData {
  const out = new ImageData(src.width, src.height);
  const table = exposureTable(stops);
  const a = src.data;
  const b = out.data;
  for (let i = 0; i < a.length; i += 4) {
    b[i] = table[a[i]];
    b[i + 1] = table[a[i + 1]];
    b[i + 2] = table[a[i + 2]];
    b[i + 3] = 255;
  }
  return out;
}

/** False colour of a grayscale image (its red channel) through a colour map. */
export function applyColourMap(src: ImageData, name: ColourMap): ImageData {
  const out = new ImageData(src.width, src.height);
  const table = colourTable(name);
  const a = src.data;
  const b = out.data;
  for (let i = 0; i < a.length; i += 4) {
    const k = a[i] * 3;
    b[i] = table[k];
    b[i + 1] = table[k + 1];
    b[i + 2] = table[k + 2];
    b[i + 3] = 255;
  }
  return out;
}
