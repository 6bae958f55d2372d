// The playground's editor: CodeMirror 6 with JavaScript (and acorn), bundled by build.mjs into one
// browser module (vendor/codemirror/codemirror.min.js) that labd serves.
export { EditorView, basicSetup } from "codemirror";
export { EditorState } from "@codemirror/state";
export { keymap } from "@codemirror/view";
export { javascript } from "@codemirror/lang-javascript";
export { lintGutter, setDiagnostics } from "@codemirror/lint";
// acorn parses a script before it runs live, so a syntax error is shown at its line
// (a browser's import() of a module that does not parse says what, not where).
export { parse } from "acorn";
