// Undo and redo of the page's own edits (`POST /v1/volumes/{name}/undo`, docs/editing.md).
//
// The server undoes one edit by its version, whatever was committed since (later edits over
// the same bricks are applied again), and an undo's version given to the same route makes the
// edit again (redo); the redo's version undoes it once more. So the page keeps two stacks of
// versions: `undo` holds, for each of its edits in effect, the version that takes it back (the
// edit's, or its last redo's); `redo` holds the versions of the undo commits it made. A new edit
// clears `redo`, as in every editor. Nothing else is needed: the server knows the rest.

import { ApiError, editErrorWords } from "./api";

/** The answer of `POST .../undo`: an edit's answer with the edits applied again. */
export interface UndoAnswer {
  version: number;
  replayed?: number;
}

interface Stacks {
  undo: number[];
  redo: number[];
}

export class UndoStack {
  private stacks: Stacks = { undo: [], redo: [] };

  /** Restores stacks kept by `save` (for the browser session, per volume). */
  static from(json: string | null): UndoStack {
    const s = new UndoStack();
    if (!json) return s;
    try {
      const v = JSON.parse(json) as Partial<Stacks>;
      const ints = (a: unknown): number[] =>
        Array.isArray(a) ? a.filter((x): x is number => Number.isInteger(x) && x > 0) : [];
      s.stacks = { undo: ints(v.undo), redo: ints(v.redo) };
    } catch {
      // Not ours: start empty.
    }
    return s;
  }

  save(): string {
    return JSON.stringify(this.stacks);
  }

  /** The page committed an edit as `version`. */
  edited(version: number): void {
    this.stacks.undo.push(version);
    this.stacks.redo.length = 0;
  }

  /** The version to send to undo the last edit in effect, or null. */
  get nextUndo(): number | null {
    return this.stacks.undo.at(-1) ?? null;
  }

  /** The version to send to make the last undone edit again, or null. */
  get nextRedo(): number | null {
    return this.stacks.redo.at(-1) ?? null;
  }

  /** The undo of `nextUndo` was committed as `version`. */
  undone(version: number): void {
    this.stacks.undo.pop();
    this.stacks.redo.push(version);
  }

  /** The redo of `nextRedo` was committed as `version` (which undoes it next time). */
  redone(version: number): void {
    this.stacks.redo.pop();
    this.stacks.undo.push(version);
  }

  /**
   * The server refused to take back `version` for good (409: undone or reverted already, not
   * an edit, compacted away): drop it so that the next press reaches the one before.
   */
  drop(version: number): void {
    this.stacks.undo = this.stacks.undo.filter((v) => v !== version);
    this.stacks.redo = this.stacks.redo.filter((v) => v !== version);
  }
}

/** What an undo or redo did, in words ("Undone (version 7); 1 later edit applied again."). */
export function undoWords(what: "undo" | "redo", answer: UndoAnswer): string {
  const n = answer.replayed ?? 0;
  const done = what === "undo" ? "Undone" : "Redone";
  const again =
    n === 0 ? "no later edit over it" : n === 1 ? "1 later edit applied again" : `${n} later edits applied again`;
  return `${done} as version ${answer.version}; ${again}.`;
}

/** A refused undo or redo, in words, with the server's reason (403: another's edit; 409: undone already...). */
export function undoErrorWords(what: "undo" | "redo", version: number, e: unknown): string {
  const verb = what === "undo" ? "undo" : "redo";
  if (e instanceof ApiError) {
    switch (e.status) {
      case 403:
        return `The server refused to ${verb} version ${version} (403 Forbidden): ${e.detail}`;
      case 409:
        return `Version ${version} cannot be ${what === "undo" ? "undone" : "redone"} (409 Conflict): ${e.detail}. It was taken off the list.`;
      case 422:
        return `The ${verb} would cost too much (422): ${e.detail}`;
      default:
        return editErrorWords(e).replace("The edit", `The ${verb}`);
    }
  }
  return `The ${verb} could not be sent: ${e instanceof Error ? e.message : String(e)}.`;
}
