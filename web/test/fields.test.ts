// fields.ts: the field paths below are the forms the server's 400 responses use (docs/api.md's
// field names, docs/scenes.md's USD refusals); the expected inputs are read off them by hand.
import assert from "node:assert/strict";
import { describe, test } from "node:test";

import { fieldHead, fieldSetting } from "../src/fields";

describe("fieldHead", () => {
  test("a USD refusal's prim and attribute belong to the scene input", () => {
    assert.equal(fieldHead("scene:/World/Looks/Wood/Texture.inputs:file"), "scene");
    assert.equal(fieldHead("scene:shot.usda.subLayers[0]"), "scene");
    assert.equal(fieldHead("scene:/Thing.clips[default].templateAssetPath"), "scene");
    assert.equal(fieldHead("scene"), "scene");
  });
  test("other fields keep their first name", () => {
    assert.equal(fieldHead("scene_sha256"), "scene_sha256");
    assert.equal(fieldHead("name"), "name");
    assert.equal(fieldHead("settings.width"), "settings");
    assert.equal(fieldHead("after[1]"), "after");
    assert.equal(fieldHead(""), "");
  });
});

describe("fieldSetting", () => {
  test("a settings field names its setting", () => {
    assert.equal(fieldSetting("settings.width"), "width");
    assert.equal(fieldSetting("settings.frames[2]"), "frames");
    assert.equal(fieldSetting("settings.aovs.albedo"), "aovs");
  });
  test("any other field names no setting", () => {
    assert.equal(fieldSetting("scene:/World.inputs:file"), "");
    assert.equal(fieldSetting("name"), "");
  });
});
