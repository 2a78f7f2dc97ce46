// The cards list: a "Tick all on this page" button for the bulk form. Without script the
// button stays hidden and cards are ticked one by one.
"use strict";
(function () {
  var button = document.getElementById("select-page");
  if (!button) { return; }
  var boxes = document.querySelectorAll('input[type="checkbox"][form="bulk-cards"]');
  button.hidden = false;
  button.addEventListener("click", function () {
    var tick = Array.prototype.some.call(boxes, function (box) { return !box.checked; });
    boxes.forEach(function (box) { box.checked = tick; });
    button.textContent = tick ? "Untick all on this page" : "Tick all on this page";
  });
})();
