// ESLint's flat config for the lab's own JavaScript: the pages' scripts (labd/web/static,
// not its vendor/ folder, which build.mjs makes from npm), their unit tests in Node
// (tests/js/pages) and this folder's build scripts.
//
// Run from the repository's root, as `make lint` does:
//   web/node_modules/.bin/eslint --config web/eslint.config.mjs
// (with --config, ESLint takes the paths below from the working directory).
import js from "@eslint/js";
import globals from "globals";

// No CDN: a page's module comes from this lab, never from another host (DESIGN.md).
const NO_CDN = "no CDN: every script a page loads is served by the lab (web/build.mjs)";
const REMOTE = "/^(https?:)?\\/\\//";

// what `make lint` names on ESLint's command line (PATHS in the Makefile)
const OURS = ["labd/web/static/**/*.js", "tests/js/pages/**/*.mjs", "web/*.mjs"];

export default [
  { ignores: ["labd/web/static/vendor/**", "**/node_modules/**", "build/**"] },
  { files: OURS, ...js.configs.recommended },
  {
    files: OURS,
    rules: {
      eqeqeq: ["error", "smart"],
      "no-var": "error",
      "prefer-const": ["error", { destructuring: "all" }],
      "no-shadow": ["error", { builtinGlobals: false }],
      "no-implicit-globals": "error",
      "no-unused-vars": ["error", { args: "after-used", argsIgnorePattern: "^_", caughtErrors: "none" }],
      // The house's one concept per function: a page's start reads as a list of its parts.
      "max-lines-per-function": ["error", { max: 80, skipBlankLines: true, skipComments: true }],
      "max-depth": ["error", 4],
      "no-restricted-syntax": [
        "error",
        { selector: `ImportDeclaration[source.value=${REMOTE}]`, message: NO_CDN },
        { selector: `ImportExpression[source.value=${REMOTE}]`, message: NO_CDN },
        { selector: `ExportNamedDeclaration[source.value=${REMOTE}]`, message: NO_CDN },
      ],
    },
  },
  {
    files: ["labd/web/static/**/*.js"],
    languageOptions: {
      ecmaVersion: 2024,
      sourceType: "module",
      // uPlot is a classic script of the trial and generic live pages (vendor/uplot)
      globals: { ...globals.browser, uPlot: "readonly" },
    },
  },
  {
    files: ["tests/js/pages/**/*.mjs", "web/*.mjs"],
    languageOptions: { ecmaVersion: 2024, sourceType: "module", globals: globals.node },
  },
];
