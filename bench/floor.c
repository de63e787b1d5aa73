/* The machine's floor for a 1 kHz loop (bench/floor.py): a compiled loop that sleeps to
 * absolute 1 ms deadlines (clock_nanosleep, TIMER_ABSTIME, CLOCK_MONOTONIC) and does nothing
 * else, as cyclictest measures a timer's latency, with the overrun policy of the package's
 * DeadlinePacer (a wake-up after the next deadline skips the passed ones and counts them).
 *
 *   floor DURATION_S [SCHED_FIFO_PRIORITY]
 *
 * Prints one JSON object: cycles released, deadlines missed, the longest run of consecutive
 * missed deadlines, the fraction of deadlines released (what the loop's "answered in time"
 * counts when every released cycle answers), the period between releases and the wake-up
 * lateness after the deadline (us: p50, p99, max). Exit 3 when SCHED_FIFO is refused. */
#define _GNU_SOURCE
#include <errno.h>
#include <sched.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#define PERIOD_NS 1000000LL

static int64_t now_ns(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (int64_t)t.tv_sec * 1000000000LL + t.tv_nsec;
}

static int cmp(const void *a, const void *b) {
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

/* The q-quantile of the n sorted values v, interpolated as numpy's percentile does. */
static double quantile(const double *v, long n, double q) {
    if (n == 0) return 0.0 / 0.0;
    double pos = q * (double)(n - 1);
    long i = (long)pos;
    double f = pos - (double)i;
    return i + 1 < n ? v[i] + f * (v[i + 1] - v[i]) : v[i];
}

int main(int argc, char **argv) {
    if (argc < 2) {
        fprintf(stderr, "usage: floor DURATION_S [SCHED_FIFO_PRIORITY]\n");
        return 2;
    }
    double duration = atof(argv[1]);
    int prio = argc > 2 ? atoi(argv[2]) : 0;
    if (prio > 0) {
        struct sched_param p = {.sched_priority = prio};
        if (sched_setscheduler(0, SCHED_FIFO, &p) != 0) {
            fprintf(stderr, "SCHED_FIFO %d: %s\n", prio, strerror(errno));
            return 3;
        }
    }
    long cap = (long)(duration * 1e3) + 16;
    double *period = malloc(sizeof(double) * cap), *late = malloc(sizeof(double) * cap);
    if (!period || !late) return 4;
    int64_t t0 = now_ns() + PERIOD_NS, end = t0 + (int64_t)(duration * 1e9), last = -1;
    long k = 0, cycles = 0, missed = 0, max_run = 0, np = 0, nl = 0;
    for (;;) {
        int64_t d = t0 + k * PERIOD_NS;
        struct timespec ts = {d / 1000000000LL, d % 1000000000LL};
        while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL) == EINTR) {}
        int64_t now = now_ns();
        long j = k + (now - d) / PERIOD_NS;      /* the newest deadline passed */
        long m = j - k;
        missed += m;
        if (m > max_run) max_run = m;
        if (nl < cap) late[nl++] = (double)(now - (t0 + j * PERIOD_NS)) * 1e-3;
        if (last >= 0 && np < cap) period[np++] = (double)(now - last) * 1e-3;
        last = now;
        cycles++;
        k = j + 1;
        if (now >= end) break;
    }
    qsort(period, np, sizeof(double), cmp);
    qsort(late, nl, sizeof(double), cmp);
    printf("{\"cycles\": %ld, \"missed_deadlines\": %ld, \"max_consecutive_missed\": %ld, "
           "\"answered_fraction\": %.6f, \"period_p50_us\": %.3f, \"period_p99_us\": %.3f, "
           "\"period_max_us\": %.3f, \"wake_late_p50_us\": %.3f, \"wake_late_p99_us\": %.3f, "
           "\"wake_late_max_us\": %.3f, \"sched_fifo_priority\": %d}\n",
           cycles, missed, max_run, (double)cycles / (double)(cycles + missed),
           quantile(period, np, 0.5), quantile(period, np, 0.99), np ? period[np - 1] : 0.0,
           quantile(late, nl, 0.5), quantile(late, nl, 0.99), nl ? late[nl - 1] : 0.0, prio);
    return 0;
}
