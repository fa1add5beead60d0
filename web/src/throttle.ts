// Runs an async task on request, at most one at a time and at most once per interval; requests
// made meanwhile coalesce into one follow-up run. Keeps live views from flooding the server.

export class Throttled {
  private running = false;
  private pending = false;
  private lastStart = 0;
  private timer: number | undefined;
  private stopped = false;

  constructor(
    private readonly task: () => Promise<void>,
    private readonly minIntervalMs: number,
  ) {}

  request(): void {
    if (this.stopped) return;
    if (this.running || this.timer !== undefined) {
      this.pending = true;
      return;
    }
    const wait = this.lastStart + this.minIntervalMs - performance.now();
    if (wait > 0) {
      this.timer = window.setTimeout(() => {
        this.timer = undefined;
        void this.run();
      }, wait);
    } else {
      void this.run();
    }
  }

  /** Runs now (after the current run, if any), ignoring the interval: for final states. */
  async flush(): Promise<void> {
    if (this.timer !== undefined) {
      window.clearTimeout(this.timer);
      this.timer = undefined;
    }
    while (this.running) await new Promise((r) => setTimeout(r, 20));
    await this.run();
  }

  stop(): void {
    this.stopped = true;
    if (this.timer !== undefined) window.clearTimeout(this.timer);
  }

  private async run(): Promise<void> {
    if (this.stopped) return;
    this.running = true;
    this.pending = false;
    this.lastStart = performance.now();
    try {
      await this.task();
    } finally {
      this.running = false;
    }
    if (this.pending) this.request();
  }
}
