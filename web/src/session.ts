// Signing in with an API token. Once the server has tokens every API request needs one, but
// EventSource and image requests cannot send an Authorization header; so the dashboard trades
// the token for an HttpOnly session cookie (POST /api/v1/session) that every same-origin request
// then carries. The first 401 shows the sign-in dialog; "Sign out" clears the cookie.

import { ApiError, onUnauthorized, signIn, signOut } from "./api";
import { h, setText } from "./dom";
import { setConnection } from "./ui";

// The cookie is HttpOnly (scripts cannot see it), so the dashboard remembers that it signed in.
const FLAG = "renderfarm.session";

let dialog: HTMLDialogElement | null = null;
let hooks: { stop: () => void; reload: () => void } | null = null;

function remembered(): boolean {
  try {
    return localStorage.getItem(FLAG) === "1";
  } catch {
    return false;
  }
}

function remember(on: boolean): void {
  try {
    if (on) localStorage.setItem(FLAG, "1");
    else localStorage.removeItem(FLAG);
  } catch {
    // storage disabled: the Sign out control shows only until the page is reloaded
  }
}

function signOutControl(): void {
  const end = document.querySelector(".topbar-end");
  let button = document.getElementById("sign-out") as HTMLButtonElement | null;
  if (!remembered()) {
    button?.remove();
    return;
  }
  if (button || !end) return;
  button = h("button", { type: "button", id: "sign-out", class: "button small secondary", onclick: doSignOut }, "Sign out");
  end.appendChild(button);
}

async function doSignOut(): Promise<void> {
  try {
    await signOut();
  } catch (e) {
    setConnection(false, (e as Error).message);
    return;
  }
  remember(false);
  signOutControl();
  hooks?.reload(); // without the cookie the view's first request answers 401: sign-in form
}

function showSignIn(): void {
  if (dialog?.open) return;
  hooks?.stop(); // no polling or streams behind the dialog
  // A 401 means the cookie, if any, is stale (revoked token, or a farm without tokens now):
  // clear it, so that it cannot outlive its use.
  const cleared = signOut().catch(() => undefined);
  remember(false);
  signOutControl();
  const input = h("input", {
    type: "password",
    id: "session-token",
    name: "token",
    autocomplete: "current-password",
    required: true,
    spellcheck: "false",
    "aria-describedby": "session-error",
  });
  const error = h("p", { id: "session-error", class: "alert", role: "alert", hidden: true });
  const button = h("button", { type: "submit", class: "button" }, "Sign in");
  const form = h(
    "form",
    { class: "session-form", method: "dialog" },
    h("h2", { id: "session-title" }, "Sign in"),
    h("p", { class: "muted small" }, "This server needs an API token (", h("code", {}, "renderfarm token create NAME"), ")."),
    h("div", { class: "field" }, h("label", { for: "session-token" }, "API token"), input),
    error,
    h("div", { class: "actions" }, button),
  );
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    button.disabled = true;
    try {
      await cleared;
      await signIn(input.value);
    } catch (e) {
      error.hidden = false;
      setText(error, e instanceof ApiError ? e.message : String(e));
      input.select();
      input.focus();
      return;
    } finally {
      button.disabled = false;
    }
    remember(true);
    dialog?.close();
    dialog?.remove();
    dialog = null;
    setConnection(true);
    signOutControl();
    hooks?.reload();
  });
  dialog?.remove();
  dialog = h("dialog", { class: "session-dialog", "aria-labelledby": "session-title" }, form);
  // Escape would leave an empty page behind: the dialog stays until the user signs in.
  dialog.addEventListener("cancel", (event) => event.preventDefault());
  document.body.appendChild(dialog);
  dialog.showModal();
  input.focus();
}

/** Wires the sign-in dialog to 401 answers; `stop` unmounts the view, `reload` routes again. */
export function initSession(stop: () => void, reload: () => void): void {
  hooks = { stop, reload };
  onUnauthorized(showSignIn);
  signOutControl();
}
