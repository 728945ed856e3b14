/*
 * libups-ecb: the admission analysis of declared streams in integer arithmetic, the same as
 * ups/rt (_analysis.py, _frames.py, _priority.py) computes with Fractions.
 *
 * Units. Every time is an integer count of units of g / (10 * bitrate) ms, g = gcd(bitrate,
 * 10000): the bit time is tau = 10000 / g units and 100 us is S = bitrate / g units, both
 * integers, so every quantity of the analysis is exact: a frame of n bits takes n * tau, a
 * period, deadline or jitter of P (x 100 us) is P * S. This is the least common unit of the
 * bit time and 100 us (N = 10 * bitrate / g units a ms; a bit time at 500 kbit/s or 8 Mbit/s),
 * and Python's scaling by the lcm of the denominators gives the same integers up to a common
 * factor, so every comparison (r <= d, the least r - d) comes out the same.
 *
 * The recurrences. w = base + sum_k ceil((w + J_k + a) / T_k) C_k (a = tau or 0) is solved
 * without a division of w but the first: as T_k = P_k S and J_k = j_k S, the count ceil((w +
 * J_k + a) / T_k) is ceil((v + j_k) / P_k) with v = ceil((w + a) / S) (w + a in 100 us, rounded
 * up, kept as w grows by each C_k); each stream k of the sum keeps the threshold n_k P_k - j_k
 * that v must pass for its count n_k to grow (4 bytes a stream, in 31 bits). The counts
 * start at 1 and only grow (from one instance of the stream analysed to the next too: its
 * queuing times grow), each step justified by a w no larger than the least fixed point, so
 * they stop exactly there. A response is only followed as far as its question needs: the
 * verdict r <= d stops as soon as a queuing time passes the deadline; the busy period of a
 * level (the same for every candidate of Audsley's search there) is found once.
 *
 * Bounds (bitrate 1 .. 2^32 - 1, anything uint32_t holds; P <= 65535, jitter <= 255, frames
 * <= 255, a frame <= 736 bits: 64 bytes, 29-bit identifier, CAN FD, worst stuffing; at most
 * 255 streams): T (period), D < 2^16 * 2^32 = 2^48;  J < 2^8 * 2^32 = 2^40;  tau <= 10000;
 * C (all frames of an event) <= 255 * 736 * 10000 < 2^31;  B (longest frame) < 2^23.
 * The horizon H = 2^30 S (2^30 x 100 us, 29.8 hours): a busy period, queuing time or response
 * past H counts as unbounded. H < 2^62; w stops as soon as it passes a limit <= H (by one
 * C_k), v <= 2^30 + 10000 and a threshold < v + 2^16 (both in 31 bits); an instance q of a
 * busy period t <= H has q T_m < t + J_m: every sum stays below 2^63.
 *
 * Utilisation. sum C_k / T_k < 1 exactly when sum C_k / P_k < S. That sum is taken as integer
 * parts plus fractions rounded up to 32 bits, which bounds it within 255 * 2^-32. When the bound
 * does not decide, either the utilisation is >= 1 (Python: None), or 1 - U < 255 * 2^-32 / S
 * and every fixed point x >= B + U x is >= B / (1 - U) > 130 S 2^32 / 255 > 2 H (B >= 130
 * units): unbounded here too. A set below 1 has every subset below 1: the admission tests it
 * once.
 *
 * So the one difference from Python: a finite response time past H is taken as unbounded. H
 * is beyond any deadline (6553.5 ms at most), and for Python to reach it, the busy period alone
 * holds more than 16384 instances of the stream (periods are at most 6553.5 ms), each its own
 * fixed point.
 *
 * No heap, no library call but libgcc's 64-bit product, no floating point; the stack holds 5
 * bytes per stream (UPS_ECB_RT_MAX of them) and a few scalars.
 */
#include "ups_ecb_rt.h"

/* 11-bit identifiers: only ups_ecb_rt_response asks for them (0 without UPS_ECB_RT_ANALYZE) */
#define RT_ID11(flags) (UPS_ECB_RT_ANALYZE && ((flags) & UPS_ECB_RT_ID11) != 0u)

#define RT_OVER INT64_MAX /* past the limit asked for (or the horizon) */
#define RT_NONE 0xFFFFu   /* no stream (an index never used) */
#define RT_FIRST 0x02u
#define RT_LAST 0x7Fu

/* One analysis: the streams, the bus, and the work arrays of the caller's stack. */
typedef struct {
    const ups_ecb_stream_t *s;
    uint8_t *live;  /* the streams of the level analysed first, in Audsley's order */
    int32_t *next;  /* by position in live: the threshold of v for the next count */
    uint32_t tau;   /* units a bit (<= 10000) */
    uint32_t scale; /* S: units in 100 us (<= bitrate) */
    uint32_t block; /* B: the longest frame of the format (< 2^23) */
    unsigned flags;
    int64_t horizon; /* H = 2^30 S */
    int64_t level;   /* the sum of C over the level's streams */
    int64_t busy;    /* the level's busy period: 0 not found yet, RT_OVER unbounded */
} rt_t;

/* A core that divides (any but an Arm one without a divide instruction, as Cortex-M0+ is);
 * UPS_ECB__SOFT_DIV takes the shifts and subtractions on any, to test them. */
#if !defined(UPS_ECB__SOFT_DIV) && (!defined(__arm__) || defined(__ARM_FEATURE_IDIV))
#define RT_DIVIDES 1
#else
#define RT_DIVIDES 0
#endif

uint32_t ups_ecb__div32(uint32_t n, uint32_t d, uint32_t *rem)
{
#if RT_DIVIDES
    *rem = n % d;
    return n / d;
#else
    uint32_t q = 0u;
    uint32_t bit = 1u;
    while ((d >> 31) == 0u && (d << 1) <= n) { /* d under n's top bit: as many steps */
        d <<= 1;
        bit <<= 1;
    }
    for (; bit != 0u; bit >>= 1, d >>= 1) {
        if (n >= d) {
            n -= d;
            q |= bit;
        }
    }
    *rem = n;
    return q;
#endif
}

/* v = ceil(@p x / @p s) for 1 <= x and v < 2^31, with @p rem = v s - x: 32-bit division when
 * x fits, else by shifts and subtractions (no 64-bit division: a libgcc call on a 32-bit core). */
static int32_t rt_ceil(int64_t x, uint32_t s, uint32_t *rem)
{
    uint64_t n = (uint64_t)x - 1u;
    uint32_t q = 0u;
    if ((n >> 32) == 0u) {
        q = ups_ecb__div32((uint32_t)n, s, rem);
    } else {
        uint64_t d = (uint64_t)s << 30;
        for (uint32_t bit = 1u << 30; bit != 0u; bit >>= 1, d >>= 1) {
            if (n >= d) {
                n -= d;
                q |= bit;
            }
        }
        *rem = (uint32_t)n;
    }
    *rem = s - 1u - *rem;
    return (int32_t)(q + 1u);
}

/* The length of one frame of @p size bytes in bits, interframe space included, as
 * ups/rt/_frames.py's frame_bits(size, id_bits, "worst", fd) or _tindell_frame_bits; 0 when the
 * format cannot carry @p size. */
static unsigned rt_frame_bits(unsigned size, unsigned flags)
{
    unsigned id11 = RT_ID11(flags); /* an 11-bit identifier takes 19 bits less (20 stuffed) */
    if ((flags & UPS_ECB_RT_FD) != 0u) {
        static const uint8_t fd_sizes[16] = {0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64};
        unsigned i = 0u;
        while (i < 16u && fd_sizes[i] < size) {
            i++;
        }
        if (i == 16u) {
            return 0u;
        }
        unsigned dynamic = 41u - 19u * id11 + 8u * fd_sizes[i];
        unsigned crc = fd_sizes[i] <= 16u ? 17u : 21u;
        unsigned fixed = 4u + crc + (4u + crc + 3u) / 4u;
        return dynamic + (dynamic - 1u) / 4u + fixed + 13u;
    }
    if (size > 8u) {
        return 0u;
    }
    unsigned stuffed = 54u - 20u * id11 + 8u * size;
#if UPS_ECB_RT_ANALYZE
    if ((flags & UPS_ECB_RT_TINDELL1994) != 0u) {
        return stuffed + 13u + stuffed / 5u;
    }
#endif
    return stuffed + 13u + (stuffed - 1u) / 4u;
}

/* C of stream @p s, its one frame in @p frame; 0 when Python would not take the stream. */
static uint32_t rt_cost(const rt_t *rt, const ups_ecb_stream_t *s, uint32_t *frame)
{
    unsigned size = s->size;
    unsigned frames = 1u;
    if (s->etag >= UPS_ECB_RT_LARGE_ETAG) {
        size = (rt->flags & UPS_ECB_RT_FD) != 0u ? 64u : 8u;
        frames = s->size;
    }
    *frame = rt_frame_bits(size, rt->flags) * rt->tau;
    if (s->period == 0u || s->deadline == 0u) {
        return 0u;
    }
    return *frame * frames;
}

/* The bus, and the sum of every stream's C; 0 for invalid input. */
static int rt_setup(rt_t *rt, const ups_ecb_stream_t *s, unsigned count, uint32_t bitrate,
                    unsigned flags)
{
    unsigned tindell_fd = UPS_ECB_RT_TINDELL1994 | UPS_ECB_RT_FD;
    uint32_t g = bitrate;
    uint32_t b = 10000u;
    if (bitrate == 0u || (flags & tindell_fd) == tindell_fd) {
        return 0;
    }
    while (b != 0u) { /* g = gcd(bitrate, 10000) */
        uint32_t r;
        (void)ups_ecb__div32(g, b, &r);
        g = b;
        b = r;
    }
    rt->s = s;
    rt->tau = ups_ecb__div32(10000u, g, &b);
    rt->scale = ups_ecb__div32(bitrate, g, &b);
    rt->flags = flags;
    rt->block = rt_frame_bits((flags & UPS_ECB_RT_FD) != 0u ? 64u : 8u, flags) * rt->tau;
    rt->horizon = (int64_t)rt->scale << 30;
    rt->level = 0;
    for (unsigned k = 0u; k < count; k++) {
        uint32_t c = rt_cost(rt, &s[k], &b);
        if (c == 0u) {
            return 0;
        }
        rt->level += c;
    }
    return 1;
}

/* Is the utilisation of the first @p n streams of live (but @p skip) below 1? Also 0 when the
 * bound does not decide (see the head comment: the horizon is passed then). */
static int rt_below_one(const rt_t *rt, unsigned n, unsigned skip)
{
    uint32_t whole = 0u;    /* the integer parts so far: below S */
    uint32_t fraction = 0u; /* in units of 2^-32 */
    for (unsigned p = 0u; p < n; p++) {
        unsigned k = rt->live[p];
        uint32_t period = rt->s[k].period; /* < 2^16 */
        uint32_t r;
        if (k == skip) {
            continue;
        }
        uint32_t q = ups_ecb__div32(rt_cost(rt, &rt->s[k], &r), period, &r);
        uint32_t high = ups_ecb__div32(r << 16, period, &r); /* r < period: in 32 bits */
        uint32_t low = ups_ecb__div32(r << 16, period, &r);
        uint32_t f = ((high << 16) | low) + (r != 0u ? 1u : 0u); /* rounded up: < 2^32 - 2^15 */
        fraction += f;
        q += fraction < f ? 1u : 0u; /* the carry (q < 2^31) */
        if (q >= rt->scale - whole) {
            return 0;
        }
        whole += q;
    }
    return 1;
}

/* The counts of the first @p n streams of live but @p skip start at 1 (v >= 1 passes the
 * threshold of count 0, -j_k); @p skip's never grows. */
static void rt_start(rt_t *rt, unsigned n, unsigned skip)
{
    for (unsigned p = 0u; p < n; p++) {
        const ups_ecb_stream_t *s = &rt->s[rt->live[p]];
        rt->next[p] = rt->live[p] == skip ? INT32_MAX : (int32_t)s->period - s->jitter;
    }
}

/* From @p w = base + sum n_k C_k, the least fixed point of w = base + sum_k ceil((w + J_k +
 * @p a) / T_k) C_k over the first @p n streams of live (their thresholds in next, as rt_start
 * made them); RT_OVER when it passes @p limit (<= H). v follows w without a division of w:
 * w + a = v S - rem, 0 <= rem < S, and each C_k added is q S + r. */
static int64_t rt_fix(rt_t *rt, unsigned n, uint32_t a, int64_t w, int64_t limit)
{
    uint32_t rem;
    if (w > limit) {
        return RT_OVER;
    }
    int32_t v = rt_ceil(w + a, rt->scale, &rem); /* <= 2^30 + 10000 */
    int moved = 1;
    while (moved) {
        moved = 0;
        for (unsigned p = n; p-- > 0u;) { /* from the shortest deadline and period up */
            while (v > rt->next[p]) {
                const ups_ecb_stream_t *s = &rt->s[rt->live[p]];
                uint32_t part;
                uint32_t c = rt_cost(rt, s, &part);
                rt->next[p] += s->period;
                w += c;
                if (w > limit) {
                    return RT_OVER;
                }
                v += (int32_t)ups_ecb__div32(c, rt->scale, &part);
                if (part > rem) {
                    v++;
                    rem += rt->scale;
                }
                rem -= part;
                moved = 1;
            }
        }
    }
    return w;
}

/* Worst-case response of stream @p m below the others of the first @p n of live, in units, if
 * it is at most @p cap (<= H); else RT_OVER. As _analysis.py's _response_time. */
static int64_t rt_response(rt_t *rt, unsigned n, unsigned m, int64_t cap)
{
    const ups_ecb_stream_t *sm = &rt->s[m];
    uint32_t frame;
    int64_t cost = rt_cost(rt, sm, &frame);
    if (rt->busy == RT_OVER) { /* a utilisation of 1 or more */
        return RT_OVER;
    }
#if UPS_ECB_RT_ANALYZE
    if ((rt->flags & UPS_ECB_RT_TINDELL1994) != 0u) { /* paper 000: J_m left out, one instance */
        rt_start(rt, n, m);
        int64_t w = rt_fix(rt, n, rt->tau, rt->block + rt->level - frame, cap - frame);
        return w == RT_OVER ? w : w + frame;
    }
#endif
    int64_t period = (int64_t)sm->period * rt->scale;
    int64_t jitter = (int64_t)sm->jitter * rt->scale;
    int64_t w = rt->block + rt->level - frame; /* its other frames go first */
    if (rt->busy == 0) { /* the level's busy period, once for all its candidates */
        rt_start(rt, n, RT_NONE);
        rt->busy = rt_fix(rt, n, 0u, rt->block + rt->level, rt->horizon);
        if (rt->busy == RT_OVER) {
            return RT_OVER;
        }
    }
    rt_start(rt, n, m);
    int64_t worst = 0;
    int64_t within = cap - jitter - (int64_t)frame; /* the response within cap: w - q T_m */
    for (int64_t at = 0;; at += period) {           /* at: q T_m */
        w = rt_fix(rt, n, rt->tau, w, at < rt->horizon - within ? within + at : rt->horizon);
        if (w == RT_OVER) {
            return RT_OVER;
        }
        if (jitter + w - at + frame > worst) {
            worst = jitter + w - at + frame;
        }
        if (at + period >= rt->busy + jitter) { /* instance q + 1 is not in it */
            return worst;
        }
        w += cost;
    }
}

static int rt_invalid(unsigned count, unsigned *miss, uint16_t *response_10us)
{
    *miss = count > 0u ? count - 1u : 0u;
    *response_10us = 0u;
    return 0;
}

int ups_ecb_rt_admit(ups_ecb_stream_t *streams, unsigned count, uint32_t bitrate, unsigned fd,
                     unsigned *miss, uint16_t *response_10us)
{
    uint8_t live[UPS_ECB_RT_MAX]; /* [0, n): the level's candidates in Python's unplaced
                                   * order ((deadline, period, index) descending); [n, count):
                                   * the streams placed, the highest priority first */
    int32_t next[UPS_ECB_RT_MAX];
    rt_t rt;
    rt.live = live;
    rt.next = next;
    if (count == 0u || count > UPS_ECB_RT_MAX ||
        !rt_setup(&rt, streams, count, bitrate, fd ? UPS_ECB_RT_FD : 0u)) {
        return rt_invalid(count, miss, response_10us);
    }
    for (unsigned i = 0u; i < count; i++) {
        /* insertion: i goes after every one that sorts above it (ties keep the index order,
         * reversed: the higher index first) */
        const ups_ecb_stream_t *me = &streams[i];
        unsigned at = i;
        while (at > 0u) {
            const ups_ecb_stream_t *o = &streams[live[at - 1u]];
            if (me->deadline < o->deadline ||
                (me->deadline == o->deadline && me->period < o->period)) {
                break;
            }
            live[at] = live[at - 1u];
            at--;
        }
        live[at] = (uint8_t)i;
    }
    /* a set below 1 has every subset below 1; one above has every candidate unbounded */
    rt.busy = rt_below_one(&rt, count, RT_NONE) ? 0 : RT_OVER;
    for (unsigned n = count; n > 0u; n--) { /* level n: live[n - 1] is to be placed */
        unsigned p = 0u;
        while (p < n && rt_response(&rt, n, live[p], (int64_t)streams[live[p]].deadline * rt.scale) == RT_OVER) {
            p++;
        }
        if (p == n) { /* none fits: Python names the one that misses by the least, the first
                       * of equals. The first and the last first (often it is one of them): the
                       * first bounded one exactly, then only one that misses by less (by as
                       * little, before the one found) */
            unsigned worst = 0u; /* (all unbounded: the first) */
            int64_t worst_r = RT_OVER;
            int64_t margin = 0;
            for (unsigned i = 0u; i < n; i++) {
                p = i == 1u ? n - 1u : (i == 0u ? 0u : i - 1u);
                int64_t d = (int64_t)streams[live[p]].deadline * rt.scale;
                int64_t cap = rt.horizon;
                int64_t by = margin - (p > worst ? 1 : 0);
                if (worst_r != RT_OVER && by < cap - d) {
                    cap = d + by;
                }
                int64_t r = rt_response(&rt, n, live[p], cap);
                if (r != RT_OVER) {
                    worst = p;
                    worst_r = r;
                    margin = r - d;
                }
            }
            *miss = live[worst];
            *response_10us = 0xFFFFu; /* past 655.34 ms, or unbounded */
            if (worst_r < (int64_t)6554 * rt.scale) {
                /* ceil(100 r / N) = ceil(10 r / S) = 10 v - floor(10 rem / S), r = v S - rem */
                uint32_t rem;
                int32_t tens = 10 * rt_ceil(worst_r, rt.scale, &rem);
                tens -= rt_ceil((int64_t)10 * rem + 1, rt.scale, &rem) - 1;
                *response_10us = (uint16_t)(tens < 0xFFFF ? tens : 0xFFFF);
            }
            return 0;
        }
        uint32_t frame;
        rt.level -= rt_cost(&rt, &streams[live[p]], &frame);
        for (; p + 1u < n; p++) { /* to live[n - 1]; the others keep their order */
            uint8_t chosen = live[p];
            live[p] = live[p + 1u];
            live[p + 1u] = chosen;
        }
        rt.busy = 0; /* the next level's busy period: not found yet */
    }
    if (count > RT_LAST - RT_FIRST + 1u) { /* Audsley's ordering has no room: ValueError */
        return rt_invalid(count, miss, response_10us);
    }
    for (unsigned p = 0u; p < count; p++) {
        streams[live[p]].priority = (uint8_t)(RT_FIRST + p);
    }
    return 1;
}

#if UPS_ECB_RT_ANALYZE
uint64_t ups_ecb_rt_response(const ups_ecb_stream_t *streams, unsigned count, uint32_t bitrate,
                             unsigned flags, uint64_t *response)
{
    uint8_t live[255];
    int32_t next[255];
    rt_t rt;
    rt.live = live;
    rt.next = next;
    if (count == 0u || count > 255u || !rt_setup(&rt, streams, count, bitrate, flags)) {
        return 0u;
    }
    for (unsigned i = 0u; i < count; i++) {
        live[i] = (uint8_t)i; /* the given order: the ones before stream i are above it */
    }
    rt.level = 0;
    for (unsigned m = 0u; m < count; m++) {
        uint32_t frame;
        rt.level += rt_cost(&rt, &streams[m], &frame);
        /* davis2007 counts stream m's own utilisation, tindell1994 not */
        int tindell = (flags & UPS_ECB_RT_TINDELL1994) != 0u;
        rt.busy = rt_below_one(&rt, m + 1u, tindell ? m : RT_NONE) ? 0 : RT_OVER;
        int64_t r = rt_response(&rt, m + 1u, m, rt.horizon);
        response[m] = r == RT_OVER ? UINT64_MAX : (uint64_t)r;
    }
    return 10u * (uint64_t)rt.scale;
}
#endif
