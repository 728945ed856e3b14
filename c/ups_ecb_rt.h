/*
 * libups-ecb: the admission analysis of declared real-time streams, in integer arithmetic
 * (ups_ecb_rt.c). The same verdicts and priorities as the Python analysis (ups/rt, used by
 * broker/_admission.py) for the same declarations. A pure function: usable on its own.
 */
#ifndef UPS_ECB_RT_H
#define UPS_ECB_RT_H

#include <stdint.h>

/** The most streams ups_ecb_rt_admit analyses (its work arrays on the stack hold 5 bytes per
 *  stream): 127, one more than the priorities 0x02..0x7F, so that every count the Python
 *  CAN-ECB can be asked about gets its answer. 1..255; a board may set it to
 *  UPS_ECB_STREAMS + 1 (the declared streams and the one being declared). */
#ifndef UPS_ECB_RT_MAX
#define UPS_ECB_RT_MAX 127
#endif
#if UPS_ECB_RT_MAX < 1 || UPS_ECB_RT_MAX > 255
#error "UPS_ECB_RT_MAX must be 1..255"
#endif

/** 1 (the default): ups_ecb_rt_response is compiled (the analysis of streams in a given order,
 *  paper 000's method and 11-bit identifiers too: for tools and tests); 0 leaves it out, and
 *  what only it needs: the admission (ups_ecb_rt_admit) is the same either way. */
#ifndef UPS_ECB_RT_ANALYZE
#define UPS_ECB_RT_ANALYZE 1
#endif

/** One declared stream, as DECLARE carries it (times in units of 100 us). */
typedef struct {
    uint16_t etag;     /* etags from 0x3000 carry transfers: size is then frames per event */
    uint8_t txnode;
    uint8_t size;      /* bytes 0..8 below 0x3000; frames 1..255 from 0x3000 */
    uint16_t period;   /* >= 1 */
    uint16_t deadline; /* >= 1 */
    uint8_t jitter;
    uint8_t priority;  /* out: the priority granted, 0x02..0x7F */
} ups_ecb_stream_t;

/** The first etag whose streams are transfers of full frames (p.LARGE_FIRST_ETAG). */
#define UPS_ECB_RT_LARGE_ETAG 0x3000u

/** Decide whether the @p count streams (sorted by (etag, txnode), as the Python CAN-ECB sorts
 *  them) are schedulable on a bus of @p bitrate bit/s (@p fd: CAN FD frames) by Audsley's
 *  assignment with the revised response-time analysis (Davis et al. 2007), as ups/rt's
 *  assign_priorities(first=0x02, last=0x7F) does. Returns 1 and writes every stream's priority
 *  when it is; 0 when not, with @p miss the index of the stream that would miss its deadline
 *  and @p response_10us its worst-case response in units of 10 us, rounded up (0xFFFF:
 *  unbounded or larger; never 0). Writes no priority when it returns 0.
 *
 *  @p response_10us 0 is Python's ValueError: more streams than priorities (Audsley found an
 *  ordering of more than 126 streams), or a declaration Python's decoder never lets through
 *  (period or deadline 0, size 0 from 0x3000, more than 8 bytes below it, count 0 or above
 *  UPS_ECB_RT_MAX, bitrate 0); @p miss is then count - 1 (0 when count is 0), and the Python
 *  CAN-ECB's Refuse names the stream being declared. */
int ups_ecb_rt_admit(ups_ecb_stream_t *streams, unsigned count, uint32_t bitrate, unsigned fd,
                     unsigned *miss, uint16_t *response_10us);

/** libups-ecb's 32-bit division (internal): @p n / @p d (d > 0), the remainder in @p rem. A
 *  core with no divide instruction (Cortex-M0+) does it by shifts and subtractions here, not
 *  by libgcc's __aeabi_uidiv (266 bytes); any other divides. */
uint32_t ups_ecb__div32(uint32_t n, uint32_t d, uint32_t *rem);

/* Flags of ups_ecb_rt_response. */
#define UPS_ECB_RT_DAVIS2007 0u   /**< the revised analysis (Davis et al. 2007), the default */
#define UPS_ECB_RT_TINDELL1994 1u /**< paper 000's Table 1 (classic frames only) */
#define UPS_ECB_RT_FD 2u          /**< CAN FD frames (davis2007 only) */
#define UPS_ECB_RT_ID11 4u        /**< 11-bit identifiers (else 29-bit, as UPS uses) */

/** Analyse @p count (1..255) streams in the given priority order (index 0 highest), blocking by
 *  the longest frame of the format, as ups/rt's analyze(specs, bitrate, method, id_bits, fd=)
 *  does: @p response[i] is stream i's worst-case response time in units of 1/N ms, where N is
 *  the return value, or UINT64_MAX when unbounded (Python's None; also a response beyond the
 *  horizon of ups_ecb_rt.c, 29.8 hours). Returns 0 (and writes nothing) for invalid input: as
 *  ups_ecb_rt_admit's, or tindell1994 with CAN FD or more than 8 bytes. The priority fields
 *  are not used. */
#if UPS_ECB_RT_ANALYZE
uint64_t ups_ecb_rt_response(const ups_ecb_stream_t *streams, unsigned count, uint32_t bitrate,
                             unsigned flags, uint64_t *response);
#endif

#endif /* UPS_ECB_RT_H */
