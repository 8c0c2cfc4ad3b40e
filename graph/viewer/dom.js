/* The one DOM helper of the pages and the result view: el(tag, attrs, ...children).
 *
 * attrs: "class" sets className, "text" textContent, "onX" adds a listener for event X, anything
 * else is an attribute (true gives an empty one); null, undefined and false are left out, as are
 * such children. Children may be nodes, strings, numbers or arrays of them.
 *
 *   const { el } = window.AcinoDom;
 *   el("p", { class: "hint" }, "Frame ", el("strong", { text: "3" }));
 */
(function () {
  "use strict";

  function el(tag, attrs, ...children) {
    const node = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs || {})) {
      if (v === null || v === undefined || v === false) continue;
      if (k === "class") node.className = v;
      else if (k === "text") node.textContent = v;
      else if (k.startsWith("on")) node.addEventListener(k.slice(2), v);
      else node.setAttribute(k, v === true ? "" : v);
    }
    for (const c of children.flat()) {
      if (c === null || c === undefined || c === false) continue;
      node.append(c instanceof Node ? c : document.createTextNode(String(c)));
    }
    return node;
  }

  window.AcinoDom = { el };
})();
