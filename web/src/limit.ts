// How many requests the streamer keeps in flight, adapted to the server's 503s and 429s: the
// rule of the Rust streamer (`client/src/streamer/limit.rs`), so a browser and a native client
// share a busy server the same way.
//
// Why: the server answers 503 with Retry-After rather than queue CPU work (mesh tiles, grid
// regions) without bound, and its queue is small. A fixed number of requests per page overflows
// it as soon as a few viewers share a server, and every refused request comes back after its
// pause. Halving the limit on an overload lets the pages share the queue; growing it by one after
// a window of successes (as many as the limit) finds the room again when the load goes away.

/**
 * Additive increase, multiplicative decrease (as TCP paces its congestion window). The limit
 * starts at the maximum, never exceeds it and never falls below one. One overload halves it
 * once: a refusal of a request started before the last cut was caused by the load that cut
 * already answered, so it does not cut again (otherwise one burst of refusals would take the
 * limit down to one at once).
 */
export class InFlightLimit {
  private maxValue: number;
  private limit: number;
  /** Successes since the limit last changed. */
  private successes = 0;
  /** When the limit was last cut (performance.now() milliseconds), or null if never. */
  private cutAt: number | null = null;

  constructor(max: number) {
    this.maxValue = Math.max(1, Math.floor(max));
    this.limit = this.maxValue;
  }

  /** Requests that may run at once now. */
  get(): number {
    return this.limit;
  }

  get max(): number {
    return this.maxValue;
  }

  /**
   * A new maximum (the page learned it speaks HTTP/2, say). A limit never cut follows it; one
   * cut keeps what it learned, under the new maximum.
   */
  set max(max: number) {
    this.maxValue = Math.max(1, Math.floor(max));
    this.limit = this.cutAt === null ? this.maxValue : Math.min(this.limit, this.maxValue);
  }

  /** The server refused (503 or 429) a request started at `started`, at `now`. */
  overloaded(started: number, now: number): void {
    if (this.cutAt !== null && started <= this.cutAt) return;
    this.limit = Math.max(1, Math.floor(this.limit / 2));
    this.successes = 0;
    this.cutAt = now;
  }

  /** The server answered a request: after as many successes as the limit, grow it by one. */
  succeeded(): void {
    if (this.limit >= this.maxValue) return;
    this.successes++;
    if (this.successes >= this.limit) {
      this.limit++;
      this.successes = 0;
    }
  }
}
