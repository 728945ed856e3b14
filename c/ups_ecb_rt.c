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
 * Bounds (bitrate 1 .. 2^32 - 1, anything uint32_t holds; P <= 65535, jitter <= 255, frames
 * <= 255, a frame <= 736 bits: 64 bytes, 29-bit identifier, CAN FD, worst stuffing; at most
 * 255 streams):
 *   T (period), D < 2^16 * 2^32 = 2^48;  J < 2^8 * 2^32 = 2^40;  tau <= 10000 < 2^14;
 *   C (all frames of an event) <= 255 * 736 * 10000 < 2^31;  B (longest frame) < 2^23;
 *   sum of the C_k < 255 * 2^31 < 2^39.
 * The horizon H = 2^62: a busy period or queuing time whose iteration passes H counts as
 * unbounded. A step of a recurrence computes x' = base + sum_k ceil((x + J_k + a) / T_k) C_k,
 * always from x <= H (checked before the step; a = tau or 0), and only over a set whose
 * utilisation sum C_k / T_k is below 1 (checked first), so C_k < T_k: the dividend x + J_k + a
 * + T_k - 1 < 2^62 + 2^49, and each term is < x + J_k + a + T_k < 2^62 + 2^49. The sum stops
 * adding as soon as it passes H, so it is at most H + one term < 2^63 + 2^49. Davis's instance
 * q < ceil((t + J_m) / T_m) of a busy period t <= H has q C_m < t + J_m and q T_m < t + J_m,
 * so its base B + q C_m + (frames - 1) C_frame and start (+ the C_k above) are < 2^62 + 2^42;
 * a response (J_m + w + C_frame, w <= H) is < 2^62 + 2^41, so r + d (comparing r - d) < 2^63;
 * the rounding to 10 us takes r / N first. Nothing passes 2^64.
 *
 * Utilisation. sum C_k / T_k >= 1 exactly when sum 10000 n_k / P_k >= bitrate (n_k the bits
 * of all frames of stream k). That sum is taken as integer parts (10000 n_k < 2^31: with 255
 * streams < 2^39) plus fractions to 96 bits, in three 32-bit limbs (a remainder r_k < P_k <
 * 2^16, so r_k * 2^32 < 2^48; a limb's sum < 255 * 2^32 < 2^40), which bounds it within
 * 255 * 2^-96. When the bound does not decide, |bitrate - sum| < 255 * 2^-96: either the
 * utilisation is >= 1 (Python: None), or 1 - U < 255 * 2^-96 / bitrate and every fixed point
 * x >= B + U x is >= B / (1 - U) > 130 * 10000 / g * bitrate * 2^96 / 255 >= 5098 * 2^96 > H
 * (10000 * bitrate / g >= 10000, B >= 130 bit times): unbounded here too.
 *
 * So the one difference from Python: a finite response time whose busy period or queuing time
 * passes H is taken as unbounded. With N <= 8 * 10^7 units a ms (any bitrate up to 8 Mbit/s),
 * H is more than 5.7 * 10^10 ms (1.8 years; 5.7 * 10^14 ms at 8 Mbit/s, where a unit is the bit
 * time): beyond any deadline (6553.5 ms at most), and for Python to reach it, the busy period
 * alone holds more than 8.7 million instances of the stream (periods are at most 6553.5 ms),
 * each its own fixed-point iteration.
 *
 * No heap, no library call, no floating point; the stack holds two bytes per stream
 * (UPS_ECB_RT_MAX each) and a few scalars.
 */
#include "ups_ecb_rt.h"

/* 11-bit identifiers: only ups_ecb_rt_response asks for them (0 without UPS_ECB_RT_ANALYZE) */
#define RT_ID11(flags) (UPS_ECB_RT_ANALYZE && ((flags) & UPS_ECB_RT_ID11) != 0u)

#define RT_HORIZON ((uint64_t)1 << 62)
#define RT_UNBOUNDED UINT64_MAX
#define RT_FIRST 0x02u
#define RT_LAST 0x7Fu

typedef struct {
    uint32_t tau;   /* units a bit (<= 10000) */
    uint32_t scale; /* units in 100 us (<= bitrate) */
    uint32_t block; /* B: the longest frame of the format (< 2^23) */
    unsigned flags;
} rt_bus_t;

typedef struct {
    uint32_t c;  /* every frame of an event (< 2^31) */
    uint32_t cf; /* one frame */
    uint64_t t, j;
    uint32_t bits; /* bits of every frame (c / tau) */
} rt_msg_t;

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

/* n / d (d > 0) and n % d in @p rem. A machine of 32-bit words has no 64-bit division: the
 * compiler would call libgcc's (__aeabi_uldivmod, __udivmoddi4: about 600 bytes of Cortex-M0+
 * code), so it is done here by shifts and subtractions (32-bit division when both fit);
 * a 64-bit machine divides. Exact either way. */
static uint64_t rt_div(uint64_t n, uint64_t d, uint64_t *rem)
{
#if UINTPTR_MAX > 0xFFFFFFFFu && !defined(UPS_ECB__SOFT_DIV) /* (that: to test the other) */
    *rem = n % d;
    return n / d;
#else
    uint64_t q = 0u;
    if ((n >> 32) == 0u && (d >> 32) == 0u) {
        uint32_t r32;
        q = ups_ecb__div32((uint32_t)n, (uint32_t)d, &r32);
        n = r32;
    } else {
        uint64_t bit = 1u;
        while ((d >> 63) == 0u && (d << 1) <= n) {
            d <<= 1;
            bit <<= 1;
        }
        for (; bit != 0u; bit >>= 1, d >>= 1) {
            if (n >= d) {
                n -= d;
                q |= bit;
            }
        }
    }
    *rem = n;
    return q;
#endif
}

static uint32_t rt_gcd(uint32_t a, uint32_t b)
{
    while (b != 0u) {
        uint32_t r;
        (void)ups_ecb__div32(a, b, &r);
        a = b;
        b = r;
    }
    return a;
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

static int rt_bus(rt_bus_t *bus, uint32_t bitrate, unsigned flags)
{
    unsigned tindell_fd = UPS_ECB_RT_TINDELL1994 | UPS_ECB_RT_FD;
    if (bitrate == 0u || (flags & tindell_fd) == tindell_fd) {
        return 0;
    }
    uint32_t g = rt_gcd(bitrate, 10000u);
    uint32_t r;
    bus->tau = ups_ecb__div32(10000u, g, &r);
    bus->scale = ups_ecb__div32(bitrate, g, &r);
    bus->flags = flags;
    bus->block = rt_frame_bits((flags & UPS_ECB_RT_FD) != 0u ? 64u : 8u, flags) * bus->tau;
    return 1;
}

/* Stream @p s as the analysis sees it; 0 when Python would not take it. */
static int rt_msg(const rt_bus_t *bus, const ups_ecb_stream_t *s, rt_msg_t *m)
{
    unsigned size = s->size;
    unsigned frames = 1u;
    if (s->etag >= UPS_ECB_RT_LARGE_ETAG) {
        size = (bus->flags & UPS_ECB_RT_FD) != 0u ? 64u : 8u;
        frames = s->size;
    }
    unsigned bits = rt_frame_bits(size, bus->flags);
    if (bits == 0u || frames == 0u || s->period == 0u || s->deadline == 0u) {
        return 0;
    }
    m->cf = bits * bus->tau;
    m->bits = bits * frames;
    m->c = m->cf * frames;
    m->t = (uint64_t)s->period * bus->scale;
    m->j = (uint64_t)s->jitter * bus->scale;
    return 1;
}

/* Is stream @p k above stream @p m? In the given order (placed NULL): the ones before it; in
 * Audsley's search: every unplaced one but m. */
static int rt_above(unsigned k, unsigned m, const uint8_t *placed)
{
    if (placed == 0) {
        return k < m;
    }
    return k != m && placed[k] == 0u;
}

/* Is the utilisation of the streams above @p m (and of m too when @p with_m) below 1? Also 0
 * when the bound does not decide (see the head comment: the horizon is passed then). Adds the
 * C_k of the streams above m to @p hp_sum. */
static int rt_below_one(const rt_bus_t *bus, const ups_ecb_stream_t *s, unsigned n, unsigned m,
                        const uint8_t *placed, int with_m, uint32_t bitrate, uint64_t *hp_sum)
{
    uint64_t whole = 0u;
    uint64_t limb[3] = {0u, 0u, 0u}; /* the fractions' bits 1..32, 33..64, 65..96 */
    uint64_t inexact = 0u;
    for (unsigned k = 0u; k < n; k++) {
        rt_msg_t x;
        int above = rt_above(k, m, placed);
        if (!(above || (with_m && k == m)) || !rt_msg(bus, &s[k], &x)) {
            continue;
        }
        if (above) {
            *hp_sum += x.c; /* < 255 * 2^31 */
        }
        uint32_t a = 10000u * x.bits; /* < 2^31 */
        uint32_t p = s[k].period;     /* < 2^16 */
        uint32_t r;
        whole += ups_ecb__div32(a, p, &r);
        for (unsigned i = 0u; i < 3u; i++) { /* long division, 32 bits (two 16) at a time */
            uint32_t high = ups_ecb__div32(r << 16, p, &r); /* r < p < 2^16: in 32 bits */
            uint32_t low = ups_ecb__div32(r << 16, p, &r);
            limb[i] += (high << 16) | low;
        }
        inexact += r != 0u ? 1u : 0u;
    }
    /* the sum is at most whole + (limbs + inexact / 2^96), which is below the integer bitrate
     * exactly when its integer part is; else U >= 1, or undecided (past the horizon) */
    limb[2] += inexact;
    limb[1] += limb[2] >> 32;
    limb[0] += limb[1] >> 32;
    return whole + (limb[0] >> 32) < bitrate;
}

/* One step: base + sum over the streams above m (and m when @p with_m) of
 * ceil((x + J_k + add) / T_k) C_k; RT_UNBOUNDED once past the horizon. */
static uint64_t rt_step(const rt_bus_t *bus, const ups_ecb_stream_t *s, unsigned n, unsigned m,
                        const uint8_t *placed, int with_m, uint64_t base, uint64_t x,
                        uint64_t add)
{
    uint64_t sum = base;
    for (unsigned k = 0u; k < n && sum <= RT_HORIZON; k++) {
        rt_msg_t y;
        if ((rt_above(k, m, placed) || (with_m && k == m)) && rt_msg(bus, &s[k], &y)) {
            uint64_t r;
            sum += rt_div(x + y.j + add + y.t - 1u, y.t, &r) * y.c;
        }
    }
    return sum <= RT_HORIZON ? sum : RT_UNBOUNDED;
}

/* Least fixed point from @p start of w = base + sum_{hp} ceil((w + J_k + tau) / T_k) C_k. */
static uint64_t rt_queuing(const rt_bus_t *bus, const ups_ecb_stream_t *s, unsigned n,
                           unsigned m, const uint8_t *placed, uint64_t base, uint64_t start)
{
    uint64_t w = start;
    while (w <= RT_HORIZON) {
        uint64_t next = rt_step(bus, s, n, m, placed, 0, base, w, bus->tau);
        if (next == w) {
            return w;
        }
        w = next;
    }
    return RT_UNBOUNDED;
}

/* Worst-case response of stream @p m below the streams above it (rt_above), in units;
 * RT_UNBOUNDED when unbounded (or past the horizon). As _analysis.py's _response_time. */
static uint64_t rt_response(const rt_bus_t *bus, const ups_ecb_stream_t *s, unsigned n,
                            unsigned m, const uint8_t *placed, uint32_t bitrate)
{
    int with_m = 1; /* davis2007: stream m's own utilisation counts */
#if UPS_ECB_RT_ANALYZE
    int tindell = (bus->flags & UPS_ECB_RT_TINDELL1994) != 0u;
    with_m = !tindell;
#endif
    rt_msg_t me;
    uint64_t hp_sum = 0u;
    if (!rt_msg(bus, &s[m], &me) ||
        !rt_below_one(bus, s, n, m, placed, with_m, bitrate, &hp_sum)) {
        return RT_UNBOUNDED;
    }
    uint64_t before_last = me.c - me.cf;
#if UPS_ECB_RT_ANALYZE
    if (tindell) { /* paper 000 leaves out J_m */
        uint64_t base = bus->block + before_last;
        uint64_t w = rt_queuing(bus, s, n, m, placed, base, base + hp_sum);
        return w == RT_UNBOUNDED ? w : w + me.cf;
    }
#endif
    uint64_t t = bus->block + hp_sum + me.c;
    for (;;) {
        if (t > RT_HORIZON) {
            return RT_UNBOUNDED;
        }
        uint64_t next = rt_step(bus, s, n, m, placed, 1, bus->block, t, 0u);
        if (next == t) {
            break;
        }
        t = next;
    }
    uint64_t r;
    uint64_t instances = rt_div(t + me.j + me.t - 1u, me.t, &r);
    uint64_t worst = 0u;
    uint64_t w = 0u;
    for (uint64_t q = 0u; q < instances; q++) {
        uint64_t start = bus->block + q * me.c + before_last;
        uint64_t from = start + hp_sum;
        if (w > from) {
            from = w;
        }
        w = rt_queuing(bus, s, n, m, placed, start, from);
        if (w == RT_UNBOUNDED) {
            return w;
        }
        uint64_t end = me.j + w + me.cf;
        if (end > q * me.t && end - q * me.t > worst) {
            worst = end - q * me.t;
        }
    }
    return worst;
}

/* Does miss (r1, d1) come before (r2, d2) in Python's min((r is None, r - d))? */
static int rt_less(uint64_t r1, uint64_t d1, uint64_t r2, uint64_t d2)
{
    if (r1 == RT_UNBOUNDED || r2 == RT_UNBOUNDED) {
        return r1 != RT_UNBOUNDED && r2 == RT_UNBOUNDED;
    }
    return r1 + d2 < r2 + d1;
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
    rt_bus_t bus;
    uint8_t order[UPS_ECB_RT_MAX]; /* Python's unplaced: (deadline, period, index) descending */
    uint8_t placed[UPS_ECB_RT_MAX]; /* 0 unplaced, else its rank + 1 (rank 0 the highest) */
    if (count == 0u || count > UPS_ECB_RT_MAX || !rt_bus(&bus, bitrate, fd ? UPS_ECB_RT_FD : 0u)) {
        return rt_invalid(count, miss, response_10us);
    }
    for (unsigned i = 0u; i < count; i++) {
        rt_msg_t x;
        if (!rt_msg(&bus, &streams[i], &x)) {
            return rt_invalid(count, miss, response_10us);
        }
        /* insertion: i goes after every one that sorts above it (ties keep the index order,
         * reversed: the higher index first) */
        unsigned at = i;
        while (at > 0u) {
            const ups_ecb_stream_t *o = &streams[order[at - 1u]];
            const ups_ecb_stream_t *me = &streams[i];
            int before = me->deadline > o->deadline ||
                         (me->deadline == o->deadline && me->period >= o->period);
            if (!before) {
                break;
            }
            order[at] = order[at - 1u];
            at--;
        }
        order[at] = (uint8_t)i;
        placed[i] = 0u;
    }
    for (unsigned level = count; level > 0u; level--) {
        unsigned chosen = count;
        unsigned worst = count;
        uint64_t worst_r = 0u;
        uint64_t worst_d = 0u;
        for (unsigned o = 0u; o < count; o++) {
            unsigned i = order[o];
            if (placed[i] != 0u) {
                continue;
            }
            uint64_t r = rt_response(&bus, streams, count, i, placed, bitrate);
            uint64_t d = (uint64_t)streams[i].deadline * bus.scale;
            if (r != RT_UNBOUNDED && r <= d) {
                chosen = i;
                break;
            }
            if (worst == count || rt_less(r, d, worst_r, worst_d)) {
                worst = i;
                worst_r = r;
                worst_d = d;
            }
        }
        if (chosen == count) {
            uint64_t per_ms = 10u * (uint64_t)bus.scale; /* N = 10 * bitrate / g units a ms */
            *miss = worst;
            *response_10us = 0xFFFFu;
            uint64_t part;
            uint64_t ms = rt_div(worst_r, per_ms, &part);
            if (worst_r != RT_UNBOUNDED && ms < 656u) { /* else > 655.35 ms */
                uint64_t tens = ms * 100u + rt_div(part * 100u + per_ms - 1u, per_ms, &part);
                if (tens < 0xFFFFu) {
                    *response_10us = (uint16_t)tens;
                }
            }
            return 0;
        }
        placed[chosen] = (uint8_t)level;
    }
    if (count > RT_LAST - RT_FIRST + 1u) { /* Audsley's ordering has no room: ValueError */
        return rt_invalid(count, miss, response_10us);
    }
    for (unsigned i = 0u; i < count; i++) {
        streams[i].priority = (uint8_t)(RT_FIRST + placed[i] - 1u);
    }
    return 1;
}

#if UPS_ECB_RT_ANALYZE
uint64_t ups_ecb_rt_response(const ups_ecb_stream_t *streams, unsigned count, uint32_t bitrate,
                             unsigned flags, uint64_t *response)
{
    rt_bus_t bus;
    if (count == 0u || count > 255u || !rt_bus(&bus, bitrate, flags)) {
        return 0u;
    }
    for (unsigned i = 0u; i < count; i++) {
        rt_msg_t x;
        if (!rt_msg(&bus, &streams[i], &x)) {
            return 0u;
        }
    }
    for (unsigned i = 0u; i < count; i++) {
        response[i] = rt_response(&bus, streams, count, i, 0, bitrate);
    }
    return 10u * (uint64_t)bus.scale;
}
#endif
