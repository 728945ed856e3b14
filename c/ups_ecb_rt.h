/*
 * libups-ecb: the admission analysis of declared real-time streams, in integer arithmetic
 * (ups_ecb_rt.c). The same verdicts and priorities as the Python analysis (ups/rt, used by
 * broker/_admission.py) for the same declarations. A pure function: usable on its own.
 */
#ifndef UPS_ECB_RT_H
#define UPS_ECB_RT_H

#include <stdint.h>

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

/** Decide whether the @p count streams (sorted by (etag, txnode), as the Python CAN-ECB sorts
 *  them) are schedulable on a bus of @p bitrate bit/s (@p fd: CAN FD frames) by Audsley's
 *  assignment with the revised response-time analysis (Davis et al. 2007), as ups/rt's
 *  assign_priorities(first=0x02, last=0x7F) does. Returns 1 and writes every stream's priority
 *  when it is; 0 when not, with @p miss the index of the stream that would miss its deadline
 *  and @p response_10us its worst-case response in units of 10 us (0xFFFF: unbounded or
 *  larger; 0 and @p miss = count - 1 when there are more streams than priorities). */
int ups_ecb_rt_admit(ups_ecb_stream_t *streams, unsigned count, uint32_t bitrate, unsigned fd,
                     unsigned *miss, uint16_t *response_10us);

#endif /* UPS_ECB_RT_H */
