import { describe, expect, it } from "vitest";
import { InFlightLimit } from "../src/limit";

// The same sequence as the Rust limit's unit test (client/src/streamer/limit.rs), worked by hand:
// 16, a refusal halves it to 8, refusals of requests started before that cut change nothing, a
// later one halves it to 4, then 4 successes grow it to 5, 5 more to 6.
describe("the in-flight limit", () => {
  it("halves once per overload and grows by one per window of successes", () => {
    const l = new InFlightLimit(16);
    expect(l.get()).toBe(16);
    l.succeeded(); // at the maximum: nothing to grow
    expect(l.get()).toBe(16);
    l.overloaded(10, 20);
    expect(l.get()).toBe(8);
    l.overloaded(5, 21); // started before the cut at 20
    l.overloaded(20, 22); // started at the cut
    expect(l.get()).toBe(8);
    l.overloaded(21, 30);
    expect(l.get()).toBe(4);
    for (let i = 0; i < 3; i++) l.succeeded();
    expect(l.get()).toBe(4);
    l.succeeded();
    expect(l.get()).toBe(5);
    for (let i = 0; i < 5; i++) l.succeeded();
    expect(l.get()).toBe(6);
  });

  it("never falls below one nor grows past the maximum", () => {
    const l = new InFlightLimit(3);
    for (let t = 1; t <= 5; t++) l.overloaded(2 * t, 2 * t + 1);
    expect(l.get()).toBe(1);
    for (let i = 0; i < 100; i++) l.succeeded();
    expect(l.get()).toBe(3);
    expect(new InFlightLimit(0).get()).toBe(1);
  });

  it("follows a new maximum until it is cut, then stays under it", () => {
    const l = new InFlightLimit(6);
    l.max = 24;
    expect(l.get()).toBe(24);
    l.overloaded(1, 2);
    expect(l.get()).toBe(12);
    l.max = 32;
    expect(l.get()).toBe(12);
    l.max = 8;
    expect(l.get()).toBe(8);
  });
});
