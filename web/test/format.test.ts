// format.ts: every expected string below is worked out by hand from the unit rules the
// dashboard shows (tenths of a second under 10 s, whole seconds under a minute, "m min ss s"
// under an hour, "h h mm min" under two days, then days; SI prefixes by thousands; binary
// prefixes by 1024), not produced by the code.
import assert from "node:assert/strict";
import { describe, test } from "node:test";

import { ago, bytes, dateTime, duration, label, percent, si, spp } from "../src/format";

describe("duration", () => {
  test("missing or non-finite values are a dash", () => {
    for (const v of [null, undefined, NaN, Infinity, -Infinity]) assert.equal(duration(v), "-");
  });
  test("negative durations count as zero", () => {
    assert.equal(duration(-5), "0.0 s");
  });
  test("tenths of a second below ten seconds", () => {
    assert.equal(duration(0), "0.0 s");
    assert.equal(duration(0.25), "0.3 s");
    assert.equal(duration(9.5), "9.5 s");
  });
  test("whole seconds below a minute", () => {
    assert.equal(duration(10), "10 s");
    assert.equal(duration(42.4), "42 s");
    assert.equal(duration(59.4), "59 s");
  });
  test("minutes and zero-padded seconds below an hour", () => {
    assert.equal(duration(60), "1 min 00 s");
    assert.equal(duration(125), "2 min 05 s");
    assert.equal(duration(3599), "59 min 59 s");
  });
  test("hours and zero-padded minutes below two days", () => {
    assert.equal(duration(3600), "1 h 00 min");
    assert.equal(duration(3 * 3600 + 7 * 60 + 59), "3 h 07 min");
    assert.equal(duration(47 * 3600 + 59 * 60), "47 h 59 min");
  });
  test("days and hours from two days on", () => {
    assert.equal(duration(48 * 3600), "2 d 0 h");
    assert.equal(duration(3 * 86400 + 5 * 3600 + 1800), "3 d 5 h");
  });
  test("rounding carries into the next unit instead of showing 60", () => {
    assert.equal(duration(9.96), "10 s");
    assert.equal(duration(59.6), "1 min 00 s");
    assert.equal(duration(119.7), "2 min 00 s");
    assert.equal(duration(3599.6), "1 h 00 min");
  });
});

describe("ago", () => {
  const now = 1_700_000_000;
  test("a missing or zero time is a dash", () => {
    assert.equal(ago(null, now), "-");
    assert.equal(ago(undefined, now), "-");
    assert.equal(ago(0, now), "-");
  });
  test("under a second ago, and clock skew into the future, is just now", () => {
    assert.equal(ago(now - 0.5, now), "just now");
    assert.equal(ago(now + 30, now), "just now");
  });
  test("older times are a duration ago", () => {
    assert.equal(ago(now - 1, now), "1.0 s ago");
    assert.equal(ago(now - 125, now), "2 min 05 s ago");
    assert.equal(ago(now - 2 * 86400, now), "2 d 0 h ago");
  });
  test("now defaults to the current time", () => {
    assert.equal(ago(Date.now() / 1000 - 3 * 86400), "3 d 0 h ago");
  });
});

describe("percent", () => {
  test("missing or non-finite values are a dash", () => {
    for (const v of [null, undefined, NaN, Infinity]) assert.equal(percent(v), "-");
  });
  test("two decimals below ten percent, one from ten on", () => {
    assert.equal(percent(0), "0.00%");
    assert.equal(percent(0.05), "5.00%");
    assert.equal(percent(0.001234), "0.12%");
    assert.equal(percent(0.123456), "12.3%");
    assert.equal(percent(1), "100.0%");
  });
  test("the number of digits is a parameter", () => {
    assert.equal(percent(0.0001234, 3), "0.012%");
    assert.equal(percent(0.5, 1), "50%");
    assert.equal(percent(0.05, 0), "5%");
  });
});

describe("si", () => {
  test("missing or non-finite values are a dash", () => {
    for (const v of [null, undefined, NaN, -Infinity]) assert.equal(si(v), "-");
  });
  test("values below a thousand have no prefix and no trailing zeros", () => {
    assert.equal(si(0), "0");
    assert.equal(si(0.5), "0.5");
    assert.equal(si(12.5), "12.5");
    assert.equal(si(999), "999");
  });
  test("thousands take k, M, G, T with three significant digits", () => {
    assert.equal(si(1000), "1 k");
    assert.equal(si(1234567), "1.23 M");
    assert.equal(si(45_600_000_000), "45.6 G");
    assert.equal(si(7e12), "7 T");
  });
  test("the sign is kept in front of the prefixed value", () => {
    assert.equal(si(-1500), "-1.5 k");
  });
  test("the number of significant digits is a parameter", () => {
    assert.equal(si(1234567, 2), "1.2 M");
    assert.equal(si(1234567, 5), "1.2346 M");
  });
  test("rounding carries into the next prefix", () => {
    assert.equal(si(999_999), "1 M");
    assert.equal(si(999.7), "1 k");
    assert.equal(si(-999_999_999), "-1 G");
  });
});

describe("spp", () => {
  test("one decimal below 100", () => {
    assert.equal(spp(0), "0.0");
    assert.equal(spp(12.34), "12.3");
  });
  test("whole numbers with thousands separators from 100 on", () => {
    assert.equal(spp(100), "100");
    assert.equal(spp(1234.4), "1,234");
    assert.equal(spp(1_048_576), "1,048,576");
  });
});

describe("dateTime", () => {
  test("a missing or zero time is a dash", () => {
    assert.equal(dateTime(null), "-");
    assert.equal(dateTime(0), "-");
  });
  test("local time, zero padded, in the zone of the browser", () => {
    const zone = process.env.TZ;
    try {
      // Node applies a changed TZ to Date at once.
      process.env.TZ = "UTC";
      assert.equal(dateTime(946_684_800), "2000-01-01 00:00:00");
      assert.equal(dateTime(1_700_000_000), "2023-11-14 22:13:20");
      process.env.TZ = "Asia/Kolkata"; // UTC+05:30 all year
      assert.equal(dateTime(946_684_800), "2000-01-01 05:30:00");
      assert.equal(dateTime(1_700_000_000.9), "2023-11-15 03:43:20");
    } finally {
      if (zone === undefined) delete process.env.TZ;
      else process.env.TZ = zone;
    }
  });
});

describe("bytes", () => {
  test("bytes below one KiB", () => {
    assert.equal(bytes(0), "0 B");
    assert.equal(bytes(1023), "1023 B");
  });
  test("KiB and MiB with one decimal", () => {
    assert.equal(bytes(1024), "1.0 KiB");
    assert.equal(bytes(1536), "1.5 KiB");
    assert.equal(bytes(1024 * 1024), "1.0 MiB");
    assert.equal(bytes(2.5 * 1024 * 1024), "2.5 MiB");
    assert.equal(bytes(300 * 1024 * 1024), "300.0 MiB");
  });
});

describe("label", () => {
  test("snake case becomes a capitalised phrase", () => {
    assert.equal(label("noise_threshold"), "Noise threshold");
    assert.equal(label("priority"), "Priority");
  });
  test("unit suffixes become parenthesised units", () => {
    assert.equal(label("time_limit_s"), "Time limit (s)");
    assert.equal(label("fov_deg"), "Fov (deg)");
  });
  test("only a trailing unit suffix is replaced", () => {
    assert.equal(label("s_deg_min"), "S deg min");
    assert.equal(label("max_samples"), "Max samples");
  });
});
