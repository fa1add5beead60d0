// throttle.ts on a fake clock: time moves only when a test advances it, and timers fire then,
// so nothing here waits in real time.
import assert from "node:assert/strict";
import { afterEach, describe, test } from "node:test";

import { Throttled, type Clock } from "../src/throttle";

class FakeClock implements Clock {
  time = 0;
  private nextId = 1;
  private readonly timers = new Map<number, { due: number; callback: () => void }>();

  now(): number {
    return this.time;
  }
  setTimeout(callback: () => void, ms: number): number {
    const id = this.nextId++;
    this.timers.set(id, { due: this.time + ms, callback });
    return id;
  }
  clearTimeout(id: number): void {
    this.timers.delete(id);
  }
  get pendingTimers(): number {
    return this.timers.size;
  }
  /** Moves the time on by `ms`, firing the timers that fall due on the way, earliest first. */
  advance(ms: number): void {
    const end = this.time + ms;
    for (;;) {
      let next: [number, { due: number; callback: () => void }] | undefined;
      for (const t of this.timers) if (t[1].due <= end && (!next || t[1].due < next[1].due)) next = t;
      if (!next) break;
      this.timers.delete(next[0]);
      this.time = next[1].due;
      next[1].callback();
    }
    this.time = end;
  }
}

/** A task whose runs finish when the test says so; records when each run started. */
class Task {
  readonly starts: number[] = [];
  active = 0;
  maxActive = 0;
  private readonly finishers: Array<(error?: Error) => void> = [];

  constructor(private readonly clock: FakeClock) {}

  readonly run = (): Promise<void> => {
    this.starts.push(this.clock.now());
    this.active++;
    this.maxActive = Math.max(this.maxActive, this.active);
    return new Promise<void>((resolve, reject) => {
      this.finishers.push((error) => {
        this.active--;
        if (error) reject(error);
        else resolve();
      });
    });
  };

  /** Ends the oldest unfinished run (there is at most one), then lets its continuations run. */
  async finish(error?: Error): Promise<void> {
    const end = this.finishers.shift();
    assert.ok(end, "no run in progress");
    end(error);
    await settle();
  }
}

/** Lets every queued promise continuation run (a turn of the event loop, not a timed wait). */
const settle = () => new Promise<void>((resolve) => setImmediate(resolve));

function setup(intervalMs = 1000) {
  const clock = new FakeClock();
  const task = new Task(clock);
  const throttled = new Throttled(task.run, intervalMs, clock);
  return { clock, task, throttled };
}

describe("Throttled", () => {
  test("the first request runs at once, even at time zero", () => {
    const { task, throttled } = setup();
    throttled.request();
    assert.deepEqual(task.starts, [0]);
  });

  test("a request after the interval runs at once", async () => {
    const { clock, task, throttled } = setup();
    throttled.request();
    await task.finish();
    clock.advance(1000);
    throttled.request();
    assert.deepEqual(task.starts, [0, 1000]);
    assert.equal(clock.pendingTimers, 0);
  });

  test("a request just before the interval is over waits for the rest of it", async () => {
    const { clock, task, throttled } = setup();
    throttled.request();
    await task.finish();
    clock.advance(999.5);
    throttled.request();
    assert.deepEqual(task.starts, [0]);
    clock.advance(0.5);
    assert.deepEqual(task.starts, [0, 1000]);
  });

  test("requests during a run coalesce into one follow-up, a full interval after the run's start", async () => {
    const { clock, task, throttled } = setup();
    throttled.request();
    clock.advance(100);
    throttled.request();
    throttled.request();
    throttled.request();
    clock.advance(200);
    await task.finish();
    assert.deepEqual(task.starts, [0], "no follow-up before the interval is over");
    clock.advance(699);
    assert.deepEqual(task.starts, [0]);
    clock.advance(1);
    assert.deepEqual(task.starts, [0, 1000]);
    await task.finish();
    clock.advance(10_000);
    assert.deepEqual(task.starts, [0, 1000], "one follow-up for the three requests");
    throttled.request();
    assert.deepEqual(task.starts, [0, 1000, 11_000], "and later requests run again");
  });

  test("a run that outlasts the interval is followed at once by the coalesced request", async () => {
    const { clock, task, throttled } = setup();
    throttled.request();
    clock.advance(1500);
    throttled.request();
    await task.finish();
    assert.deepEqual(task.starts, [0, 1500]);
  });

  test("requests while a follow-up waits for the interval coalesce into it", async () => {
    const { clock, task, throttled } = setup();
    throttled.request();
    await task.finish();
    clock.advance(200);
    throttled.request();
    throttled.request();
    throttled.request();
    assert.equal(clock.pendingTimers, 1);
    clock.advance(800);
    assert.deepEqual(task.starts, [0, 1000]);
    await task.finish();
    clock.advance(10_000);
    assert.deepEqual(task.starts, [0, 1000]);
  });

  test("flush runs at once, ignoring the interval, and cancels the waiting follow-up", async () => {
    const { clock, task, throttled } = setup();
    throttled.request();
    await task.finish();
    clock.advance(100);
    throttled.request();
    assert.equal(clock.pendingTimers, 1);
    const flushed = throttled.flush();
    assert.deepEqual(task.starts, [0, 100]);
    assert.equal(clock.pendingTimers, 0);
    await task.finish();
    await flushed;
    clock.advance(10_000);
    assert.deepEqual(task.starts, [0, 100]);
  });

  test("flush during a run waits for it, then runs; runs never overlap", async () => {
    const { clock, task, throttled } = setup();
    throttled.request();
    clock.advance(50);
    let done = false;
    const flushed = throttled.flush().then(() => {
      done = true;
    });
    await settle();
    assert.deepEqual(task.starts, [0], "flush waits for the run in progress");
    clock.advance(50);
    await task.finish();
    assert.deepEqual(task.starts, [0, 100]);
    assert.equal(done, false, "flush resolves when its own run is over");
    await task.finish();
    await flushed;
    assert.equal(done, true);
    assert.equal(task.maxActive, 1);
  });

  test("flush also waits for the follow-up the run in progress starts", async () => {
    const { clock, task, throttled } = setup();
    throttled.request();
    clock.advance(1500);
    throttled.request();
    const flushed = throttled.flush();
    await task.finish();
    assert.deepEqual(task.starts, [0, 1500], "the coalesced follow-up, first");
    await task.finish();
    assert.deepEqual(task.starts, [0, 1500, 1500], "then the flush's own run");
    await task.finish();
    await flushed;
    assert.equal(task.maxActive, 1);
  });

  test("flush rejects with its run's failure, not with the failure of the run it waited for", async () => {
    const { task, throttled } = setup();
    // The expectations are attached before the runs end, so no rejection goes unhandled.
    const first = assert.rejects(throttled.flush(), /first run failed/);
    const second = assert.rejects(throttled.flush(), /second run failed/);
    await task.finish(new Error("first run failed"));
    await first;
    assert.deepEqual(task.starts, [0, 0], "the second flush ran after the failed run");
    await task.finish(new Error("second run failed"));
    await second;
  });

  test("a failed run does not block later requests", async () => {
    const { clock, task, throttled } = setup();
    const flushed = assert.rejects(throttled.flush(), /boom/);
    await task.finish(new Error("boom"));
    await flushed;
    clock.advance(1000);
    throttled.request();
    assert.deepEqual(task.starts, [0, 1000]);
  });

  test("stop cancels the waiting follow-up and ignores later requests and flushes", async () => {
    const { clock, task, throttled } = setup();
    throttled.request();
    await task.finish();
    clock.advance(100);
    throttled.request();
    throttled.stop();
    assert.equal(clock.pendingTimers, 0);
    clock.advance(10_000);
    throttled.request();
    await throttled.flush();
    assert.deepEqual(task.starts, [0]);
  });

  test("requests after stop schedule nothing", async () => {
    const { clock, task, throttled } = setup();
    throttled.request();
    await task.finish();
    throttled.stop();
    clock.advance(100);
    throttled.request();
    assert.equal(clock.pendingTimers, 0);
    clock.advance(10_000);
    assert.deepEqual(task.starts, [0]);
  });

  test("a request made during a run that is then stopped has no follow-up", async () => {
    const { clock, task, throttled } = setup();
    throttled.request();
    clock.advance(1500);
    throttled.request();
    throttled.stop();
    await task.finish();
    clock.advance(10_000);
    assert.deepEqual(task.starts, [0]);
    assert.equal(clock.pendingTimers, 0);
  });
});

describe("Throttled's default clock", () => {
  const g = globalThis as { window?: unknown };
  const savedWindow = g.window;
  const savedPerformance = Object.getOwnPropertyDescriptor(globalThis, "performance")!;
  afterEach(() => {
    g.window = savedWindow;
    Object.defineProperty(globalThis, "performance", savedPerformance);
  });

  test("is the page's: performance.now and window's timers", async () => {
    const times = [5_000, 30_000];
    Object.defineProperty(globalThis, "performance", { configurable: true, value: { now: () => times.shift() } });
    const calls: string[] = [];
    let delay = NaN;
    g.window = {
      setTimeout: (_callback: () => void, ms: number) => {
        delay = ms;
        calls.push("setTimeout");
        return 7;
      },
      clearTimeout: (id: number) => calls.push(`clearTimeout ${id}`),
    };
    const throttled = new Throttled(async () => {}, 60_000);
    await throttled.flush(); // starts at 5 s by performance.now
    throttled.request(); // at 30 s: the interval has 35 s to go
    assert.equal(delay, 35_000);
    throttled.stop();
    assert.deepEqual(calls, ["setTimeout", "clearTimeout 7"]);
  });
});
