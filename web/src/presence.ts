// The others on the same volume: this page tells the server where its camera is
// (`POST .../presence`, at most twice a second, and again every few seconds while it stands
// still, since the server announces a user silent for 10 s as gone), and draws each other user
// the feed's `presence` events announce as a marker with their name, in a colour of their own.

import type { Presence, Vec3 } from "./api";

/** FNV-1a, 32 bits, of a string's UTF-16 code units. */
export function fnv1a(s: string): number {
  let h = 0x811c9dc5;
  for (let i = 0; i < s.length; i++) {
    h ^= s.charCodeAt(i);
    h = Math.imul(h, 0x01000193) >>> 0;
  }
  return h >>> 0;
}

/** A user's colour: the same for the same name on every page, hues spread by a hash. */
export function colourFor(user: string): string {
  return `hsl(${fnv1a(user) % 360}, 70%, 45%)`;
}

/** Least milliseconds between two posts (the server takes 5 a second; the page sends 2). */
export const PRESENCE_INTERVAL_MS = 500;
/** A post at least this often while the camera stands still (the server forgets after 10 s). */
export const PRESENCE_KEEPALIVE_MS = 4_000;

export interface Whereabouts {
  position: Vec3;
  looking: Vec3;
}

/**
 * Posts where the camera is, throttled: the first move is sent at once, moves within
 * `interval` of the last post wait for its end and only the latest is sent; standing still,
 * the last whereabouts are sent again every `keepalive`.
 */
export class PresenceSender {
  private latest: Whereabouts | null = null;
  private lastSent = -Infinity;
  private timer: ReturnType<typeof setTimeout> | null = null;
  private keepTimer: ReturnType<typeof setInterval> | null = null;
  private stopped = false;

  constructor(
    private readonly send: (w: Whereabouts) => void,
    private readonly now: () => number = () => performance.now(),
    readonly interval = PRESENCE_INTERVAL_MS,
    readonly keepalive = PRESENCE_KEEPALIVE_MS,
  ) {
    this.keepTimer = setInterval(() => {
      if (this.latest && this.now() - this.lastSent >= this.keepalive - 1) this.flush();
    }, this.keepalive);
  }

  /** The camera moved to `w`. */
  moved(w: Whereabouts): void {
    if (this.stopped) return;
    this.latest = w;
    if (this.timer !== null) return;
    const wait = this.lastSent + this.interval - this.now();
    if (wait <= 0) this.flush();
    else this.timer = setTimeout(() => this.flush(), wait);
  }

  private flush(): void {
    this.timer = null;
    if (!this.latest || this.stopped) return;
    this.lastSent = this.now();
    this.send(this.latest);
  }

  stop(): void {
    this.stopped = true;
    if (this.timer !== null) clearTimeout(this.timer);
    if (this.keepTimer !== null) clearInterval(this.keepTimer);
  }
}

/** Where a point (level-0 voxels) appears on the canvas (CSS pixels), or null behind the camera. */
export type Projector = (p: Vec3) => { x: number; y: number } | null;

/**
 * The other users' markers: one element per user over the canvas (a dot in their colour and
 * their name), placed where their camera is.
 */
export class Cursors {
  private readonly people = new Map<string, { p: Presence; el: HTMLElement }>();

  constructor(private readonly layer: HTMLElement) {}

  /** The users shown, by name. */
  get users(): string[] {
    return [...this.people.keys()].sort();
  }

  /** A presence event: shows or moves the user's marker, or removes it when `gone`. */
  update(p: Presence, project: Projector): void {
    if (p.gone) {
      this.remove(p.user);
      return;
    }
    let entry = this.people.get(p.user);
    if (!entry) {
      const el = this.layer.ownerDocument.createElement("div");
      el.className = "cursor";
      el.dataset["user"] = p.user;
      el.style.setProperty("--colour", colourFor(p.user));
      const name = this.layer.ownerDocument.createElement("span");
      el.append(name);
      this.layer.append(el);
      entry = { p, el };
      this.people.set(p.user, entry);
    }
    entry.p = p;
    const name = entry.el.firstElementChild as HTMLElement;
    name.textContent = p.label && p.label !== p.user ? `${p.user} (${p.label})` : p.user;
    this.place(entry, project);
  }

  remove(user: string): void {
    this.people.get(user)?.el.remove();
    this.people.delete(user);
  }

  clear(): void {
    for (const u of [...this.people.keys()]) this.remove(u);
  }

  /** Places every marker again (the camera moved). */
  placeAll(project: Projector): void {
    for (const e of this.people.values()) this.place(e, project);
  }

  private place(e: { p: Presence; el: HTMLElement }, project: Projector): void {
    const at = project(e.p.position);
    e.el.hidden = at === null;
    if (at) e.el.style.transform = `translate(${at.x.toFixed(1)}px, ${at.y.toFixed(1)}px)`;
  }
}
