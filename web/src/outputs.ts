// What the job page says about a job's outputs: the numeric scale of a heat map (read from
// the PNG the server sent) and whether a completed job reached its noise target.

import { percent } from "./format";

const PNG_SIGNATURE = [0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a];

/** The tEXt chunks of a PNG (keyword -> text), read before the image data; {} when the bytes
 *  are not a PNG or are cut short. */
export function pngText(bytes: Uint8Array): Record<string, string> {
  const out: Record<string, string> = {};
  if (bytes.length < 8 || PNG_SIGNATURE.some((b, i) => bytes[i] !== b)) return out;
  const latin1 = (from: number, to: number) => String.fromCharCode(...bytes.subarray(from, to));
  let at = 8;
  while (at + 8 <= bytes.length) {
    const length = ((bytes[at] << 24) | (bytes[at + 1] << 16) | (bytes[at + 2] << 8) | bytes[at + 3]) >>> 0;
    const type = latin1(at + 4, at + 8);
    const data = at + 8;
    if (data + length > bytes.length || type === "IDAT" || type === "IEND") break;
    if (type === "tEXt") {
      const nul = bytes.subarray(data, data + length).indexOf(0);
      if (nul > 0) out[latin1(data, data + nul)] = latin1(data + nul + 1, data + length);
    }
    at = data + length + 4; // and the CRC
  }
  return out;
}

export interface Scale {
  min: number;
  max: number;
}

/** The values black and white stand for in a grey layer's PNG (renderfarm:scale_min/max, see
 *  docs/usage.md, "Outputs"); null when the PNG has no scale or a malformed one. */
export function layerScale(text: Record<string, string>): Scale | null {
  const min = Number(text["renderfarm:scale_min"]);
  const max = Number(text["renderfarm:scale_max"]);
  if (text["renderfarm:scale_max"] === undefined || !Number.isFinite(min) || !Number.isFinite(max) || max <= min) return null;
  return { min, max };
}

/** A value of a heat map's scale as its layer reads: the error in percent, spp in samples,
 *  the standard error with three significant digits. */
export function scaleValue(layer: string, value: number): string {
  if (layer === "error") return percent(value);
  if (layer === "spp") return Number.isInteger(value) ? value.toLocaleString("en") : value.toFixed(1);
  if (value === 0) return "0";
  return Math.abs(value) >= 0.01 && Math.abs(value) < 1000 ? value.toPrecision(3) : value.toExponential(2);
}

export interface Outcome {
  state: string;
  settings: { noise_threshold: number; max_spp: number; time_limit_s?: unknown };
  progress: { tiles_total: number; error: number | null };
}

/** For a completed job whose tiles did not all stop on noise (stopped at max_spp or the time
 *  limit, StopReason in states.py), a sentence saying so; null otherwise, and for a job with no
 *  noise target (noise_threshold 0 renders max_spp everywhere by design). */
export function noiseTargetShortfall(job: Outcome, stops: { reason: string | null }[]): string | null {
  const target = job.settings.noise_threshold;
  if (job.state !== "completed" || !(target > 0)) return null;
  const count = (reason: string) => stops.filter((s) => s.reason === reason).length;
  const converged = count("converged");
  const total = job.progress.tiles_total;
  if (converged >= total) return null;
  const parts: string[] = [];
  const atMax = count("max_spp");
  const atTime = count("time_limit");
  if (atMax) parts.push(`${atMax} at max_spp (${job.settings.max_spp.toLocaleString("en")} spp)`);
  if (atTime) parts.push(`${atTime} at the time limit`);
  const other = total - converged - atMax - atTime;
  if (other > 0) parts.push(`${other} otherwise`);
  const error = job.progress.error === null ? "" : `; image error ${percent(job.progress.error)}`;
  return `Completed without reaching the noise target of ${percent(target)}: ${total - converged} of ${total} tiles stopped before it, ${parts.join(", ")}${error}.`;
}

/** One ranked name of a pixel's Cryptomatte (`GET .../frames/{n}/mattes`). */
export interface MatteEntry {
  name: string;
  coverage: number;
}

/** A pixel's Cryptomatte as the viewer's pointer line says it: the node covering most of it
 *  with its share of the samples, any others of the pixel, then its material and root node
 *  ("nothing" where no sample hit anything). */
export function matteText(m: { objects: MatteEntry[]; materials: MatteEntry[]; assets: MatteEntry[] }): string {
  const share = (e: MatteEntry) => `${e.name} (${Math.round(e.coverage * 100)}%)`;
  if (m.objects.length === 0) return "nothing";
  const parts = [`object ${m.objects.map(share).join(", ")}`];
  if (m.materials.length) parts.push(`material ${share(m.materials[0])}`);
  if (m.assets.length && m.assets[0].name !== m.objects[0].name) parts.push(`asset ${share(m.assets[0])}`);
  return parts.join(" · ");
}
