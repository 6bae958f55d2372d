// What every page script shares: finding and making elements, the page's configuration
// and status line, the counters tests wait on, and saying why a page could not start.
//
// Only functions: importing this module touches no page, so the modules of the pages'
// logic that import it run in Node's test runner too (tests/js/pages).

/** The page's element with id ``id`` (null where it has none). */
export const $ = (id) => document.getElementById(id);

/** A new element with attributes (``class`` among them) and children. */
export function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") node.className = v; else node.setAttribute(k, v);
  }
  node.append(...children);
  return node;
}

/** The JSON the server put in the page's ``<script type="application/json" id=ID>``. */
export function config(id) {
  return JSON.parse($(id).textContent);
}

/** ``text`` on the page's status line (#status), its ``level`` (info, warning, error) in
 * ``data-level`` for its colour. */
export function status(text, level = "info") {
  const line = $("status");
  line.textContent = text;
  line.dataset.level = level;
}

/** One more in ``node.dataset[key]``: what a page has done (frames shown, commands sent),
 * which tests and scripts read. */
export function count(node, key) {
  node.dataset[key] = String(Number(node.dataset[key] || 0) + 1);
}

/** Run a page's ``main``; if it fails, the status line says so and the error goes on to the
 * console. */
export function start(main) {
  return main().catch((err) => {
    $("status").textContent = `the page could not start: ${err}`;
    throw err;
  });
}
