// The recruitment link's page: a participant returning in the same browser sends the token
// this browser holds (facelab's outbox keeps it), so their session - and any answers still
// waiting in the outbox under that token - comes back. Nothing else is read or sent.
"use strict";
(function () {
  const field = document.querySelector('input[name="previous_token"]');
  try {
    const token = localStorage.getItem("facelab.token");
    if (field && token) field.value = token;
  } catch (e) { /* storage blocked: join as a new browser */ }
})();
