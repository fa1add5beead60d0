// The viewer's layer switch (pages/viewer.ts): which layers a job's settings give, and the
// query each one asks the server for. The job settings are written out by hand as the server
// returns them (settings.aovs in table order, settings.light_groups as compact JSON).
import assert from "node:assert/strict";
import { describe, test } from "node:test";

import { jobLayers, layerQuery } from "../src/pages/viewer";

describe("jobLayers", () => {
  test("a job without outputs has the image and its statistics", () => {
    assert.deepEqual(
      jobLayers({}).map((l) => l.id),
      ["rgb", "error", "spp", "variance", "albedo", "normal"],
    );
  });
  test("lobes add their eight layers; light groups one layer a group, in the job's order", () => {
    const ids = jobLayers({
      aovs: "lobes,light_groups",
      light_groups: '{"key":[1],"Rim_Light":[4,5],"environment":[]}',
    }).map((l) => l.id);
    assert.deepEqual(ids.slice(6), [
      "diffuse_direct", "diffuse_indirect", "glossy_direct", "glossy_indirect",
      "transmission_direct", "transmission_indirect", "emission", "background",
      "light_group.key", "light_group.Rim_Light", "light_group.environment",
    ]);
  });
  test("light groups not known (yet): no group layers", () => {
    assert.equal(jobLayers({ aovs: "light_groups" }).filter((l) => l.id.startsWith("light")).length, 0);
  });
});

describe("layerQuery", () => {
  test("a light group's layer asks for light_group with its group", () => {
    assert.deepEqual(layerQuery("light_group.Rim_Light"), { layer: "light_group", group: "Rim_Light" });
    assert.deepEqual(layerQuery("depth"), { layer: "depth", group: "" });
  });
});
