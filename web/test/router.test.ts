// router.ts: location hashes as the dashboard's links write them ("#/jobs", "#/jobs/<id>",
// "#/jobs?state=...", "#/workers", "#/submit") and as users may type them.
import assert from "node:assert/strict";
import { describe, test } from "node:test";

import { parseRoute, section, type Route } from "../src/router";

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
    assert.deepEqual(parseRoute("#/jobs/3f2a9c"), { page: "job", jobId: "3f2a9c" });
    assert.deepEqual(parseRoute("#/jobs/a%20b%2Fc"), { page: "job", jobId: "a b/c" });
    assert.deepEqual(parseRoute("#/jobs/3f2a9c?state=done"), { page: "job", jobId: "3f2a9c" });
    assert.deepEqual(parseRoute("#/jobs/3f2a9c/extra"), { page: "job", jobId: "3f2a9c" });
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
