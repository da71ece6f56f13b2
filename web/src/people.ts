// The page's part in editing together (issue 34): who the session's token is, undo and redo of
// its own edits, the history panel and looking at an older version read-only, the others'
// cursors, notes when someone else's edit lands near the camera, and sign-in (a pasted token,
// or the OIDC provider's login). `main.ts` hands it the page's state through `PeopleHost` and
// calls it from a few hooks (the feed's events, the camera, edits, the token form).

import { ApiError, editErrorWords, type Api, type AuthInfo, type ChangeEvent, type Presence, type Vec3, type VolumeInfo } from "./api";
import type { TokenStore } from "./edit";
import { applyCommit, describe, HistoryPanel, mergeHistory, nearNote } from "./history";
import { Cursors, PresenceSender, type Projector } from "./presence";
import { beginSignIn, finishSignIn } from "./signin";
import { UndoStack, undoErrorWords, undoWords, type UndoAnswer } from "./undo";

export interface PeopleHost {
  api: Api;
  tokens: TokenStore;
  /** The volume shown. */
  volume(): VolumeInfo | null;
  /** The camera, in world units: where it is and the point it looks at. */
  camera(): { position: Vec3; looking: Vec3 };
  /** Where a world point appears on the canvas, or null behind the camera. */
  project(world: Vec3): { x: number; y: number } | null;
  /** Shows `version` read-only, or the live volume again (null). */
  show(version: number | null): void;
  /** Puts the outcome of an action into words (the edit status line). */
  say(text: string, error?: boolean): void;
  /** Shows the token prompt. */
  askToken(): void;
}

const $ = <T extends HTMLElement>(id: string) => document.getElementById(id) as T;

/** Whether keys go to a field being typed in (whose own Ctrl+Z undoes the typing). */
function typing(target: EventTarget | null): boolean {
  if (target instanceof HTMLTextAreaElement) return true;
  return target instanceof HTMLInputElement && !["checkbox", "radio", "range", "button", "submit"].includes(target.type);
}

/** How near (level-0 voxels) someone else's edit must land to the camera or its target to be noted. */
const NEAR_VOXELS = 48;

export class People {
  /** Who the session's token is (null without one, or before the server said). */
  me: string | null = null;
  auth: AuthInfo | null = null;
  /** The server's OIDC provider, from the last answer of `/v1/auth` (kept when a token is refused). */
  private oidc: AuthInfo["oidc"] = null;
  /** The version shown read-only, or null for the live volume. */
  viewing: number | null = null;
  private undo = new UndoStack();
  private readonly panel: HistoryPanel;
  private readonly cursors = new Cursors($("cursors"));
  private sender: PresenceSender | null = null;
  private busy = false;
  private noteTimer: ReturnType<typeof setTimeout> | null = null;

  constructor(private readonly host: PeopleHost) {
    this.panel = new HistoryPanel($<HTMLOListElement>("history"), {
      view: (v) => this.view(v),
      revert: (v) => void this.revert(v),
    });
    $("undo").addEventListener("click", () => void this.step("undo"));
    $("redo").addEventListener("click", () => void this.step("redo"));
    $("live").addEventListener("click", () => this.view(null));
    $("sign-in").addEventListener("click", () => this.host.askToken());
    $("sign-in-oidc").addEventListener("click", () => {
      const oidc = this.oidc;
      if (oidc) beginSignIn(oidc).catch((e: unknown) => this.host.say(`Sign-in: ${String(e)}`, true));
    });
    window.addEventListener("keydown", (e) => {
      if (!(e.ctrlKey || e.metaKey) || typing(e.target)) return;
      const k = e.key.toLowerCase();
      if (k === "z" || k === "y") {
        e.preventDefault();
        void this.step(k === "y" || e.shiftKey ? "redo" : "undo");
      }
    });
    this.updateButtons();
  }

  /**
   * Before the page reads anything: finishes a sign-in at the provider when the page is its
   * redirect back (the token is then the session's), and learns who the token is.
   */
  async start(): Promise<void> {
    try {
      // Without the token: a stale one (an expired JWT) must not hide how to sign in again.
      const first = await this.host.api.auth(true);
      this.oidc = first.oidc;
      if (first.oidc) {
        const token = await finishSignIn(first.oidc);
        if (token) this.host.tokens.set(token);
      }
    } catch (e) {
      // A refused token is the volume reads' to put into words; a failed sign-in is said here.
      if (!(e instanceof ApiError)) this.host.say(`Sign-in: ${e instanceof Error ? e.message : String(e)}`, true);
    }
    await this.whoAmI();
  }

  /** Asks the server who the session's token is (after a token was given or refused). */
  async whoAmI(): Promise<void> {
    try {
      this.auth = await this.host.api.auth();
    } catch {
      // A refused token (401) is the page's reads' to put into words and forget (main.ts):
      // forgetting it here would race them. Meanwhile nobody is signed in.
      this.auth = null;
    }
    if (this.auth) this.oidc = this.auth.oidc;
    this.me = this.auth?.user ?? null;
    $("who").textContent = this.me
      ? `Signed in as ${this.me}${this.auth?.write ? "" : " (read only)"}`
      : "Not signed in: the volume can be looked at; edits, undo and cursors need a token.";
    $("sign-in-oidc").hidden = !this.oidc;
    this.panel.writer = this.auth?.write ?? false;
    this.panel.render();
    this.restartPresence();
  }

  /** A volume was opened: its history, its undo stacks (kept for the session), presence. */
  open(v: VolumeInfo): void {
    this.viewing = null;
    this.showBanner();
    this.cursors.clear();
    this.undo = UndoStack.from(sessionStorage.getItem(this.undoKey(v.name)));
    this.updateButtons();
    this.panel.set([]);
    void this.loadHistory(v.name);
    this.restartPresence();
  }

  private undoKey(volume: string): string {
    return `isovox-undo:${volume}`;
  }

  private saveUndo(): void {
    const v = this.host.volume();
    if (v) sessionStorage.setItem(this.undoKey(v.name), this.undo.save());
    this.updateButtons();
  }

  private updateButtons(): void {
    $<HTMLButtonElement>("undo").disabled = this.undo.nextUndo === null;
    $<HTMLButtonElement>("redo").disabled = this.undo.nextRedo === null;
  }

  private async loadHistory(name: string): Promise<void> {
    try {
      const h = await this.host.api.history(name, 100);
      if (this.host.volume()?.name !== name) return;
      this.panel.set(mergeHistory(this.panel.entries, h.commits));
    } catch (e) {
      $("history-status").textContent = `History: ${e instanceof ApiError ? `${e.status} ${e.detail}` : String(e)}`;
    }
  }

  // --- hooks ------------------------------------------------------------------------------

  /** The page committed an edit. */
  edited(version: number): void {
    this.undo.edited(version);
    this.saveUndo();
  }

  /** A commit of the feed (in order, each once). */
  commit(ev: ChangeEvent): void {
    const { list, refetch } = applyCommit(this.panel.entries, ev);
    this.panel.set(list);
    const v = this.host.volume();
    if (refetch && v) void this.loadHistory(v.name);
    if (v) {
      const s = v.voxel_scale;
      const toVoxels = (p: Vec3): Vec3 => [p[0] / s[0], p[1] / s[1], p[2] / s[2]];
      const cam = this.host.camera();
      const note = nearNote(ev, this.me, [toVoxels(cam.position), toVoxels(cam.looking)], NEAR_VOXELS);
      if (note) this.note(note);
    }
  }

  /** A presence event of the feed. */
  presence(p: Presence): void {
    if (p.user === this.me) return;
    this.cursors.update(p, this.projector());
  }

  /** The camera moved (or a frame was drawn): markers follow, and the others are told. */
  cameraMoved(): void {
    this.cursors.placeAll(this.projector());
    const v = this.host.volume();
    if (!v || !this.sender) return;
    const s = v.voxel_scale;
    const c = this.host.camera();
    const voxels = (p: Vec3): Vec3 => [p[0] / s[0], p[1] / s[1], p[2] / s[2]];
    this.sender.moved({ position: voxels(c.position), looking: voxels(c.looking) });
  }

  frame(): void {
    this.cursors.placeAll(this.projector());
  }

  /** For the tests: who is shown, and the panel's rows. */
  state(): object {
    return {
      me: this.me,
      viewing: this.viewing,
      cursors: this.cursors.users,
      history: this.panel.entries.map((e) => ({ version: e.version, author: e.author ?? null, kind: e.kind ?? null, undone: e.undone ?? null, text: describe(e) })),
      nextUndo: this.undo.nextUndo,
      nextRedo: this.undo.nextRedo,
    };
  }

  // --- actions ----------------------------------------------------------------------------

  private projector(): Projector {
    const v = this.host.volume();
    if (!v) return () => null;
    const s = v.voxel_scale;
    return (p) => this.host.project([p[0] * s[0], p[1] * s[1], p[2] * s[2]]);
  }

  private restartPresence(): void {
    this.sender?.stop();
    this.sender = null;
    const v = this.host.volume();
    if (!v || !this.me) return;
    const name = v.name;
    const label = this.me;
    this.sender = new PresenceSender((w) => {
      this.host.api.presence(name, w.position, w.looking, label).catch(() => {
        // A lost cursor is not worth a word: the next move sends it again.
      });
    });
    this.cameraMoved();
  }

  private note(text: string): void {
    const el = $("note");
    el.textContent = text;
    el.hidden = false;
    if (this.noteTimer !== null) clearTimeout(this.noteTimer);
    this.noteTimer = setTimeout(() => (el.hidden = true), 6_000);
  }

  /** Undoes the page's last edit in effect, or redoes the last it undid. */
  async step(what: "undo" | "redo"): Promise<void> {
    const v = this.host.volume();
    const target = what === "undo" ? this.undo.nextUndo : this.undo.nextRedo;
    if (!v || this.busy) return;
    if (target === null) {
      this.host.say(what === "undo" ? "Nothing of yours to undo." : "Nothing to redo.");
      return;
    }
    if (!this.host.tokens.get()) {
      this.host.askToken();
      this.host.say("Enter the write token to undo your edits.");
      return;
    }
    this.busy = true;
    this.host.say(what === "undo" ? "Undoing..." : "Redoing...");
    try {
      const answer: UndoAnswer = await this.host.api.undo(v.name, target);
      if (what === "undo") this.undo.undone(answer.version);
      else this.undo.redone(answer.version);
      this.host.say(undoWords(what, answer));
    } catch (e) {
      if (e instanceof ApiError && e.status === 409) this.undo.drop(target);
      this.host.say(undoErrorWords(what, target, e), true);
    } finally {
      this.busy = false;
      this.saveUndo();
    }
  }

  /** Shows version `v` read-only, or the live volume again (null). */
  view(v: number | null): void {
    const head = this.panel.entries[0]?.version;
    this.viewing = v === head ? null : v;
    this.panel.viewing = this.viewing;
    this.panel.render();
    this.showBanner();
    this.host.show(this.viewing);
  }

  private showBanner(): void {
    const banner = $("viewing");
    banner.hidden = this.viewing === null;
    $("viewing-text").textContent = `Viewing version ${this.viewing ?? ""}, read-only`;
  }

  private async revert(to: number): Promise<void> {
    const v = this.host.volume();
    if (!v) return;
    if (!window.confirm(`Commit a new version with the content of version ${to}? Later edits stay in the history.`)) return;
    try {
      const r = await this.host.api.revert(v.name, to);
      this.view(null);
      this.host.say(`Reverted to version ${to} as version ${r.version}.`);
    } catch (e) {
      this.host.say(editErrorWords(e).replace("The edit", "The revert"), true);
    }
  }
}
