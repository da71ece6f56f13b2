// The history panel: who changed the volume, when, what and why (`GET .../history`, kept
// current from the change feed's commit events, which carry the same notes; docs/editing.md
// "History and undo"). Selecting an entry shows that version read-only; "revert to this"
// commits a version with its content.

import type { ChangeEvent, HistoryEntry, OpSummary, Vec3 } from "./api";

/** Entries kept (the newest). */
export const HISTORY_KEPT = 200;

/** `a` with `b`'s entries added (or replacing those of the same version), newest first. */
export function mergeHistory(a: readonly HistoryEntry[], b: readonly HistoryEntry[]): HistoryEntry[] {
  const byVersion = new Map<number, HistoryEntry>();
  for (const e of a) byVersion.set(e.version, e);
  for (const e of b) byVersion.set(e.version, e);
  return [...byVersion.values()].sort((x, y) => y.version - x.version).slice(0, HISTORY_KEPT);
}

/**
 * The history after the feed's commit `ev`: its entry added; for an undo its edit marked
 * undone, for a redo marked in effect again; for a revert the edits after its version marked
 * undone. `refetch` says the list should be read again from the server: after a revert an
 * edit before its version may be in effect again, which only the whole history tells.
 */
export function applyCommit(
  list: readonly HistoryEntry[],
  ev: ChangeEvent,
): { list: HistoryEntry[]; refetch: boolean } {
  const { changed, ...info } = ev;
  const entry: HistoryEntry = {
    ...info,
    bricks_changed: changed.reduce((n, level) => n + level.length, 0),
  };
  if (ev.kind === "edit") entry.undone = false;
  const mark = (e: HistoryEntry): HistoryEntry => {
    if (ev.kind === "undo" && e.version === ev.target) return { ...e, undone: true };
    if (ev.kind === "redo" && e.version === ev.target) return { ...e, undone: false };
    if (ev.kind === "revert" && ev.to !== undefined && e.version > ev.to && e.undone !== undefined) {
      return { ...e, undone: true };
    }
    return e;
  };
  return { list: mergeHistory(list.map(mark), [entry]), refetch: ev.kind === "revert" };
}

const VERBS: Record<string, string> = {
  union: "added",
  difference: "carved",
  intersection: "cut away around",
  add: "densified",
  modulate: "modulated",
};

/** The verb for an edit's operator ("carved" for difference). */
export function verb(op: string): string {
  return VERBS[op] ?? `applied ${op}`;
}

/** What a commit did, in words: "carved (difference: ellipsoid)", "undid version 7 (1 edit applied again)". */
export function describe(e: HistoryEntry | ChangeEvent): string {
  const op = (o: OpSummary) => `${verb(o.op)} (${o.op}: ${o.leaves.join(", ") || "no leaf"})`;
  const again = e.replayed ? ` (${e.replayed} later edit${e.replayed === 1 ? "" : "s"} applied again)` : "";
  switch (e.kind) {
    case "edit":
      return e.op ? op(e.op) : "edited";
    case "undo":
      return `undid version ${e.target ?? "?"}${again}`;
    case "redo":
      return `redid version ${e.target ?? "?"}${again}`;
    case "revert":
      return `reverted to version ${e.to ?? "?"}`;
    case "tag":
      return `tagged version ${e.to ?? "?"} "${e.tag ?? ""}"`;
    default:
      return "committed";
  }
}

/** Distance from point `p` to the box [min, max) (0 inside). */
export function distanceToBox(p: Vec3, box: { min: Vec3; max: Vec3 }): number {
  let d2 = 0;
  for (let a = 0; a < 3; a++) {
    const v = p[a]!;
    const lo = box.min[a]!;
    const hi = box.max[a]!;
    const d = v < lo ? lo - v : v > hi ? v - hi : 0;
    d2 += d * d;
  }
  return Math.sqrt(d2);
}

/**
 * The note for someone else's edit landing near the camera ("alice carved here"), or null: an
 * edit (or its undo or redo) by another user whose box is within `radius` voxels of `camera`
 * (level-0 voxels) or, when given, of the point the camera looks at.
 */
export function nearNote(
  ev: ChangeEvent,
  me: string | null,
  points: readonly Vec3[],
  radius: number,
): string | null {
  if (!ev.author || ev.author === me || !ev.op) return null;
  const op = ev.op;
  if (!points.some((p) => distanceToBox(p, op.box) <= radius)) return null;
  const what = ev.kind === "undo" ? `undid an edit` : ev.kind === "redo" ? `redid an edit` : verb(op.op);
  return `${ev.author} ${what} here`;
}

function time(ms: number): string {
  const d = new Date(ms);
  const two = (n: number) => String(n).padStart(2, "0");
  return `${two(d.getHours())}:${two(d.getMinutes())}:${two(d.getSeconds())}`;
}

export interface HistoryPanelActions {
  /** Show version `v` read-only. */
  view(v: number): void;
  /** Commit a version with version `v`'s content. */
  revert(v: number): void;
}

/** The list in the page: one row per commit, newest first. */
export class HistoryPanel {
  entries: HistoryEntry[] = [];
  /** The version shown read-only, if any (its row is marked). */
  viewing: number | null = null;
  /** Whether "revert to this" is offered (the token may write). */
  writer = false;

  constructor(
    private readonly list: HTMLOListElement,
    private readonly actions: HistoryPanelActions,
  ) {}

  set(entries: HistoryEntry[]): void {
    this.entries = entries;
    this.render();
  }

  render(): void {
    const doc = this.list.ownerDocument;
    const head = this.entries[0]?.version;
    this.list.replaceChildren(
      ...this.entries.map((e) => {
        const li = doc.createElement("li");
        li.dataset["version"] = String(e.version);
        li.classList.toggle("undone", e.undone === true);
        li.classList.toggle("viewing", e.version === this.viewing);
        const who = doc.createElement("b");
        who.textContent = e.author ?? "(nobody recorded)";
        const what = doc.createElement("span");
        what.textContent = ` ${describe(e)}${e.undone ? ", undone" : ""}`;
        const when = doc.createElement("small");
        when.textContent = `v${e.version} ${time(e.timestamp_ms)}`;
        li.append(when, " ", who, what);
        if (e.message) {
          const m = doc.createElement("q");
          m.textContent = e.message;
          li.append(" ", m);
        }
        const view = doc.createElement("button");
        view.type = "button";
        view.className = "view";
        view.textContent = "view";
        view.title = `Show version ${e.version} read-only`;
        view.addEventListener("click", () => this.actions.view(e.version));
        li.append(" ", view);
        if (this.writer && e.version !== head) {
          const revert = doc.createElement("button");
          revert.type = "button";
          revert.className = "revert";
          revert.textContent = "revert to this";
          revert.title = `Commit a new version with version ${e.version}'s content`;
          revert.addEventListener("click", () => this.actions.revert(e.version));
          li.append(" ", revert);
        }
        return li;
      }),
    );
  }
}
