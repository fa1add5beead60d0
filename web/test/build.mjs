// Compiles the unit tests (test/*.test.ts) and the modules they import into dist-test/, one
// bundle per test file, for `node --test` (Node 20 cannot run TypeScript itself). Type checking
// is `tsc -p test` (see package.json); esbuild only strips types and bundles.
import * as esbuild from "esbuild";
import { readdir, rm } from "node:fs/promises";

const tests = (await readdir("test")).filter((name) => name.endsWith(".test.ts"));
if (tests.length === 0) throw new Error("no test/*.test.ts files");

await rm("dist-test", { recursive: true, force: true });
await esbuild.build({
  entryPoints: tests.map((name) => `test/${name}`),
  bundle: true,
  platform: "node",
  format: "esm",
  target: ["node20"],
  sourcemap: "inline",
  outdir: "dist-test",
  logLevel: "warning",
});
