// router.ts: location hashes as the dashboard's links write them ("#/jobs", "#/jobs/<id>",
// "#/jobs?state=...", "#/workers", "#/submit") and as users may type them.
import assert from "node:assert/strict";
import { describe, test } from "node:test";

import { frameParam, jobHash, MAX_FRAME, parseRoute, section, type Route } from "../src/router";

function jobsQuery(route: Route): Record<string, string> {
  assert.equal(route.page, "jobs");
  return route.page === "jobs" ? Object.fromEntries(route.query) : {};
}

describe("parseRoute", () => {
  test("an empty hash, or only '#', is the jobs list", () => {
    for (const hash of ["", "#", "#/"]) {
      assert.deepEqual(jobsQuery(parseRoute(hash)), {}, hash);
    }
  });
  test("the jobs list keeps its query parameters, percent-decoded", () => {
    assert.deepEqual(jobsQuery(parseRoute("#/jobs")), {});
    assert.deepEqual(jobsQuery(parseRoute("#/jobs?state=running")), { state: "running" });
    assert.deepEqual(jobsQuery(parseRoute("#/jobs?state=a%20b&owner=x+y")), { state: "a b", owner: "x y" });
  });
  test("a job's page carries its id, percent-decoded", () => {
    assert.deepEqual(parseRoute("#/jobs/3f2a9c"), { page: "job", jobId: "3f2a9c", frame: null });
    assert.deepEqual(parseRoute("#/jobs/a%20b%2Fc"), { page: "job", jobId: "a b/c", frame: null });
    assert.deepEqual(parseRoute("#/jobs/3f2a9c?state=done"), { page: "job", jobId: "3f2a9c", frame: null });
    assert.deepEqual(parseRoute("#/jobs/3f2a9c/extra"), { page: "job", jobId: "3f2a9c", frame: null });
  });
  test("a job's page carries the frame its query names", () => {
    assert.deepEqual(parseRoute("#/jobs/3f2a9c?frame=12"), { page: "job", jobId: "3f2a9c", frame: 12 });
    assert.deepEqual(parseRoute("#/jobs/3f2a9c?state=done&frame=-3"), { page: "job", jobId: "3f2a9c", frame: -3 });
    assert.deepEqual(parseRoute("#/jobs/3f2a9c?frame=abc"), { page: "job", jobId: "3f2a9c", frame: null });
  });
  test("a trailing slash after jobs is the list, not a job", () => {
    assert.equal(parseRoute("#/jobs/").page, "jobs");
  });
  test("workers and submit", () => {
    assert.deepEqual(parseRoute("#/workers"), { page: "workers" });
    assert.deepEqual(parseRoute("#/submit"), { page: "submit" });
    assert.deepEqual(parseRoute("#/workers?state=idle"), { page: "workers" });
  });
  test("empty path segments and a missing leading slash are ignored", () => {
    assert.deepEqual(parseRoute("#//workers/"), { page: "workers" });
    assert.deepEqual(parseRoute("#submit"), { page: "submit" });
    assert.deepEqual(parseRoute("/workers"), { page: "workers" });
  });
  test("an unknown path is the jobs list, with its query", () => {
    assert.deepEqual(jobsQuery(parseRoute("#/nowhere")), {});
    assert.deepEqual(jobsQuery(parseRoute("#/workers2?state=done")), { state: "done" });
    assert.deepEqual(jobsQuery(parseRoute("#/nowhere/42")), {});
  });
  test("a malformed percent escape in a job id is a URIError", () => {
    assert.throws(() => parseRoute("#/jobs/%E0%A4%A"), URIError);
  });
});

describe("section", () => {
  test("a job's page belongs to the jobs section; the others are their own", () => {
    assert.equal(section(parseRoute("#/jobs/42")), "jobs");
    assert.equal(section(parseRoute("#/jobs")), "jobs");
    assert.equal(section(parseRoute("#/nowhere")), "jobs");
    assert.equal(section(parseRoute("#/workers")), "workers");
    assert.equal(section(parseRoute("#/submit")), "submit");
  });
});

describe("frameParam", () => {
  const frame = (query: string) => frameParam(new URLSearchParams(query));
  test("whole numbers, negative ones too, and surrounding blanks", () => {
    assert.equal(frame("frame=0"), 0);
    assert.equal(frame("frame=7"), 7);
    assert.equal(frame("frame=-10"), -10);
    assert.equal(frame("frame=%2012%20"), 12);
    assert.equal(frame("frame=007"), 7);
    assert.equal(frame("frame=+4"), 4); // "+" in a query is a space
  });
  test("-0 is frame 0, not negative zero", () => {
    assert.ok(Object.is(frame("frame=-0"), 0));
  });
  test("the server's range, +-1000000, and no further", () => {
    assert.equal(MAX_FRAME, 1000000);
    assert.equal(frame("frame=1000000"), 1000000);
    assert.equal(frame("frame=-1000000"), -1000000);
    assert.equal(frame("frame=1000001"), null);
    assert.equal(frame("frame=99999999"), null);
  });
  test("missing, empty or not a whole number: null", () => {
    for (const q of ["", "frame=", "frame=1.5", "frame=1e3", "frame=0x10", "frame=3a", "frame=--1", "frame=%2B4", "frames=3"]) {
      assert.equal(frame(q), null, q);
    }
  });
});

describe("jobHash", () => {
  test("a job's page, with a frame when one is given", () => {
    assert.equal(jobHash("3f2a9c"), "#/jobs/3f2a9c");
    assert.equal(jobHash("3f2a9c", null), "#/jobs/3f2a9c");
    assert.equal(jobHash("3f2a9c", 3), "#/jobs/3f2a9c?frame=3");
    assert.equal(jobHash("3f2a9c", -2), "#/jobs/3f2a9c?frame=-2");
  });
  test("parseRoute reads back what jobHash writes", () => {
    for (const [id, f] of [["a b/c", 0], ["x%y", 12], ["plain", null], ["neg", -5]] as [string, number | null][]) {
      assert.deepEqual(parseRoute(jobHash(id, f)), { page: "job", jobId: id, frame: f });
    }
  });
});
