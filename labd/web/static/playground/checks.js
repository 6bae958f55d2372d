// The playground's checks and messages (playground.js), as plain functions: whether a
// script parses and where its error goes in the editor, what the page does with each
// message of the frame the script runs in, and a trial's progress in words. Node's test
// runner checks them (tests/js/pages/playground.test.mjs) with the same acorn and
// CodeMirror the page bundles.

/** The script's syntax error as the editor marks it (``{message, line, column}``: line
 * 1-based, column 1-based or 0 for the whole line), or null when it parses. ``parse`` is
 * acorn's; the script is an ES module, as the runner imports it. */
export function syntaxError(parse, code) {
  try {
    parse(code, { ecmaVersion: "latest", sourceType: "module" });
    return null;
  } catch (err) {
    return {
      message: `SyntaxError: ${err.message.replace(/ \(\d+:\d+\)$/, "")}`,
      line: err.loc?.line ?? 1,
      column: (err.loc?.column ?? -1) + 1,
    };
  }
}

/** Where a mark of line ``line`` (1-based, held within the document) and column
 * ``column`` (1-based; 0 marks the whole line) goes in ``doc``, CodeMirror's Text. */
export function markRange(doc, line, column = 0) {
  const at = doc.line(Math.min(Math.max(line, 1), doc.lines));
  const from = column > 0 ? Math.min(at.from + column - 1, at.to) : at.from;
  const to = column > 0 ? Math.min(from + 1, at.to) : at.to;
  return { from, to: Math.max(to, from) };
}

/**
 * What the page does with a message of the runner's frame (playground_runner.html):
 * ``{do: "run"}`` (send it the script), ``{do: "print", text, level}``, ``{do: "fail",
 * printed, mark, why}`` (print, mark the line if known, stop) or ``{do: "stop", why}``;
 * null for anything else.
 */
export function fromRunner(m) {
  const message = m || {};
  switch (message.op) {
    case "ready": return { do: "run" };
    case "log": return { do: "print", text: message.text, level: message.level };
    case "error": {
      const at = message.line ? ` (line ${message.line})` : "";
      return {
        do: "fail",
        printed: `${message.text}${at}`,
        mark: message.line ? { message: message.text, line: message.line, column: message.column } : null,
        why: `the script failed${at}: ${message.text}`,
      };
    }
    case "done": return { do: "stop", why: "the script ended" };
    default: return null;
  }
}

/** A robot's bridge address, with the slot's key in its query when there is one. */
export function bridgeAddress(robots, robot, slotKey) {
  const found = robots.find((r) => r.name === robot);
  return slotKey ? `${found.bridge}?key=${encodeURIComponent(slotKey)}` : found.bridge;
}

/** A trial's progress on the status line: its words, their level, and whether it ended. */
export function trialProgress(trial) {
  const said = trial.outcome ? `${trial.outcome}: ${trial.reason}` : trial.reason || trial.status;
  return {
    text: `trial #${trial.id} ${trial.status}${said && said !== trial.status ? ` · ${said}` : ""}`,
    level: trial.outcome === "error" ? "error" : "info",
    ended: trial.status === "finished" || trial.status === "cancelled",
  };
}
