window.pageErrors = [];
window.addEventListener("error", function (event) {
  var message = (event && event.message) || "script error";
  window.pageErrors.push(message);
  document.documentElement.setAttribute("data-error", window.pageErrors.join(" | "));
  document.title = "ERROR: " + message;
  var banner = document.getElementById("error-banner");
  if (banner) { banner.textContent = "This page hit a script error: " + window.pageErrors.join("; "); banner.hidden = false; }
});
