// Number, time and state formatting shared by the pages.

export function duration(seconds: number | null | undefined): string {
  if (seconds === null || seconds === undefined || !Number.isFinite(seconds)) return "-";
  const s = Math.max(0, seconds);
  // Units are chosen after rounding, so 59.6 s is "1 min 00 s", not "60 s" (nor "0 min 60 s").
  if (Math.round(s * 10) < 100) return `${s.toFixed(1)} s`;
  const whole = Math.round(s);
  if (whole < 60) return `${whole} s`;
  const m = Math.floor(whole / 60);
  if (m < 60) return `${m} min ${String(whole % 60).padStart(2, "0")} s`;
  const hrs = Math.floor(m / 60);
  if (hrs < 48) return `${hrs} h ${String(m % 60).padStart(2, "0")} min`;
  return `${Math.floor(hrs / 24)} d ${hrs % 24} h`;
}

export function ago(unixSeconds: number | null | undefined, now = Date.now() / 1000): string {
  if (!unixSeconds) return "-";
  const d = now - unixSeconds;
  if (d < 1) return "just now";
  return `${duration(d)} ago`;
}

export function percent(fraction: number | null | undefined, digits = 2): string {
  if (fraction === null || fraction === undefined || !Number.isFinite(fraction)) return "-";
  const p = fraction * 100;
  return `${p < 10 ? p.toFixed(digits) : p.toFixed(Math.max(0, digits - 1))}%`;
}

/** 1234567 -> "1.23 M" (SI prefixes, for rates). */
export function si(value: number | null | undefined, digits = 3): string {
  if (value === null || value === undefined || !Number.isFinite(value)) return "-";
  const units = ["", "k", "M", "G", "T"];
  let v = Math.abs(value);
  let i = 0;
  while (v >= 1000 && i < units.length - 1) {
    v /= 1000;
    i++;
  }
  const sign = value < 0 ? "-" : "";
  let text = v === 0 ? "0" : v.toPrecision(digits);
  // Rounding can reach the next prefix: 999 999 is "1 M", not "1.00e+3 k".
  if (Number(text) >= 1000 && i < units.length - 1) {
    i++;
    text = "1";
  }
  if (text.includes(".") && !text.includes("e")) text = text.replace(/0+$/, "").replace(/\.$/, "");
  return `${sign}${text}${units[i] ? " " + units[i] : ""}`;
}

export function spp(value: number): string {
  return value >= 100 ? Math.round(value).toLocaleString("en") : value.toFixed(1);
}

export function dateTime(unixSeconds: number | null | undefined): string {
  if (!unixSeconds) return "-";
  const d = new Date(unixSeconds * 1000);
  const pad = (n: number) => String(n).padStart(2, "0");
  return (
    `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())} ` +
    `${pad(d.getHours())}:${pad(d.getMinutes())}:${pad(d.getSeconds())}`
  );
}

export function bytes(n: number): string {
  if (n < 1024) return `${n} B`;
  if (n < 1024 * 1024) return `${(n / 1024).toFixed(1)} KiB`;
  return `${(n / 1024 / 1024).toFixed(1)} MiB`;
}

/** "noise_threshold" -> "Noise threshold". */
export function label(name: string): string {
  const words = name.replace(/_s$/, " (s)").replace(/_deg$/, " (deg)").split("_");
  const text = words.join(" ").replace(/\bspp\b/g, "spp");
  return text.charAt(0).toUpperCase() + text.slice(1);
}
