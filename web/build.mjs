// Copies the browser files the lab's pages use (Swagger UI, ReDoc, uPlot, three.js,
// roslibjs, CodeMirror) from node_modules into labd/web/static/vendor/, which `labd serve` serves:
// nothing is fetched from a CDN.
// Run by `make setup` (npm ci, then this); the vendor folder is not committed.
// three.js comes as one minified module too (esbuild), and every script and style gets
// a gzip'd twin (NAME.gz) that the lab sends to browsers that accept it
// (labd/web/assets.py): a trial page's viewer weighs a fifth of its plain files.
import { build } from "esbuild";
import { cpSync, mkdirSync, readdirSync, readFileSync, rmSync, statSync, writeFileSync } from "node:fs";
import { dirname, join } from "node:path";
import { fileURLToPath } from "node:url";
import { gzipSync } from "node:zlib";

const here = dirname(fileURLToPath(import.meta.url));
const modules = join(here, "node_modules");
const vendor = join(here, "..", "labd", "web", "static", "vendor");

// destination (under vendor/) -> source (under node_modules/)
const FILES = {
  "swagger-ui/swagger-ui-bundle.js": "swagger-ui-dist/swagger-ui-bundle.js",
  "swagger-ui/swagger-ui.css": "swagger-ui-dist/swagger-ui.css",
  "swagger-ui/LICENSE": "swagger-ui-dist/LICENSE",
  "redoc/redoc.standalone.js": "redoc/bundles/redoc.standalone.js",
  "redoc/LICENSE": "redoc/LICENSE",
  "uplot/uPlot.iife.min.js": "uplot/dist/uPlot.iife.min.js",
  "uplot/uPlot.min.css": "uplot/dist/uPlot.min.css",
  "uplot/LICENSE": "uplot/LICENSE",
  "three/three.module.js": "three/build/three.module.js",
  "three/three.core.js": "three/build/three.core.js",
  "three/addons/controls/OrbitControls.js": "three/examples/jsm/controls/OrbitControls.js",
  "three/LICENSE": "three/LICENSE",
  "roslib/LICENSE": "roslib/LICENSE",
  "codemirror/LICENSE": "codemirror/LICENSE",
  "codemirror/LICENSE.acorn": "acorn/LICENSE",
};

rmSync(vendor, { recursive: true, force: true });
for (const [to, from] of Object.entries(FILES)) {
  const target = join(vendor, to);
  mkdirSync(dirname(target), { recursive: true });
  cpSync(join(modules, from), target);
}
// ReDoc's sidebar shows a small logo it loads from its CDN: serve it from here instead.
const LOGO = "https://cdn.redoc.ly/redoc/logo-mini.svg";
const redoc = join(vendor, "redoc", "redoc.standalone.js");
const text = readFileSync(redoc, "utf8");
if (!text.includes(LOGO)) throw new Error(`${redoc}: no ${LOGO} to replace; check the ReDoc version`);
writeFileSync(redoc, text.replaceAll(LOGO, "/static/redoc-logo.svg"));

// three.js (its module and core) as one minified module, for the trial page's 3D view.
await build({
  entryPoints: [join(modules, "three", "build", "three.module.js")],
  outfile: join(vendor, "three", "three.module.min.js"),
  bundle: true, minify: true, format: "esm", legalComments: "inline", logLevel: "warning",
});
for (const controls of ["OrbitControls", "TransformControls"]) {  // the 3D views' handles
  await build({
    entryPoints: [join(modules, "three", "examples", "jsm", "controls", `${controls}.js`)],
    outfile: join(vendor, "three", "addons", "controls", `${controls}.min.js`),
    bundle: true, minify: true, format: "esm", external: ["three"], logLevel: "warning",
  });
}
// roslibjs (npm roslib 2.x) for the live robots' pages, with its dependencies, as one
// browser module: the pages reach the robots through the bridge with it, like any client.
await build({
  entryPoints: [join(modules, "roslib", "dist", "RosLib.js")],
  outfile: join(vendor, "roslib", "roslib.min.js"),
  bundle: true, minify: true, format: "esm", platform: "browser", legalComments: "inline",
  logLevel: "warning",
});

// CodeMirror 6 (the editor of /playground, with JavaScript and its linter's marks) as one
// browser module: codemirror.mjs says what the page takes of it.
await build({
  entryPoints: [join(here, "codemirror.mjs")],
  outfile: join(vendor, "codemirror", "codemirror.min.js"),
  bundle: true, minify: true, format: "esm", platform: "browser", legalComments: "inline",
  logLevel: "warning",
});

function* files(folder) {
  for (const name of readdirSync(folder)) {
    const path = join(folder, name);
    if (statSync(path).isDirectory()) yield* files(path); else yield path;
  }
}
for (const path of files(vendor)) {
  if (/\.(js|css)$/.test(path)) writeFileSync(`${path}.gz`, gzipSync(readFileSync(path), { level: 9 }));
}

writeFileSync(join(vendor, "README"), "Built by web/build.mjs from npm packages; do not edit.\n");
console.log(`vendor: ${Object.keys(FILES).length} files in ${vendor}`);
