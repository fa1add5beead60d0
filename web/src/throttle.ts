// Runs an async task on request, at most one at a time and at most once per interval; requests
// made meanwhile coalesce into one follow-up run. Keeps live views from flooding the server.

/** The clock and timers a Throttled uses: the page's by default, fakes in the unit tests. */
export interface Clock {
  now(): number;
  setTimeout(callback: () => void, ms: number): number;
  clearTimeout(id: number): void;
}

const pageClock: Clock = {
  now: () => performance.now(),
  setTimeout: (callback, ms) => window.setTimeout(callback, ms),
  clearTimeout: (id) => window.clearTimeout(id),
};

export class Throttled {
  private running = false;
  private pending = false;
  // Never started: the first request runs at once, however soon after page load (when the
  // page clock, which starts at navigation, is still below the interval).
  private lastStart = -Infinity;
  private timer: number | undefined;
  private stopped = false;
  private current: Promise<void> | null = null;

  constructor(
    private readonly task: () => Promise<void>,
    private readonly minIntervalMs: number,
    private readonly clock: Clock = pageClock,
  ) {}

  request(): void {
    if (this.stopped) return;
    if (this.running || this.timer !== undefined) {
      this.pending = true;
      return;
    }
    const wait = this.lastStart + this.minIntervalMs - this.clock.now();
    if (wait > 0) {
      this.timer = this.clock.setTimeout(() => {
        this.timer = undefined;
        void this.start();
      }, wait);
    } else {
      void this.start();
    }
  }

  /** Runs now (after the current run, if any), ignoring the interval: for final states. */
  async flush(): Promise<void> {
    if (this.timer !== undefined) {
      this.clock.clearTimeout(this.timer);
      this.timer = undefined;
    }
    // Waits for the run in progress (and any follow-up it starts) rather than polling a timer;
    // that run's failure is its requester's, not this flush's.
    while (this.running && this.current) await this.current.catch(() => undefined);
    await this.start();
  }

  stop(): void {
    this.stopped = true;
    if (this.timer !== undefined) this.clock.clearTimeout(this.timer);
  }

  private start(): Promise<void> {
    const run = this.run();
    this.current = run;
    return run;
  }

  private async run(): Promise<void> {
    if (this.stopped) return;
    this.running = true;
    this.pending = false;
    this.lastStart = this.clock.now();
    try {
      await this.task();
    } finally {
      this.running = false;
    }
    if (this.pending) this.request();
  }
}
