// Bundles the dashboard into dist/: index.html, assets/app.js, assets/app.css.
// Type checking is `tsc --noEmit` (see package.json); esbuild only strips types and bundles.
import * as esbuild from "esbuild";
import { copyFile, mkdir, rm } from "node:fs/promises";

const watch = process.argv.includes("--watch");
const options = {
  entryPoints: { app: "src/main.ts" },
  bundle: true,
  format: "esm",
  target: ["es2020"],
  minify: !watch,
  sourcemap: true,
  outdir: "dist/assets",
  logLevel: "info",
};

await rm("dist", { recursive: true, force: true });
await mkdir("dist/assets", { recursive: true });
await copyFile("index.html", "dist/index.html");
await copyFile("src/styles.css", "dist/assets/app.css");
if (watch) {
  const context = await esbuild.context(options);
  await context.watch();
} else {
  await esbuild.build(options);
}
