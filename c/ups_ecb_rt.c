/*
 * libups-ecb: the admission analysis of declared streams in integer arithmetic.
 * SKELETON: to be completed by its owner.
 */
#include "ups_ecb_rt.h"

int ups_ecb_rt_admit(ups_ecb_stream_t *streams, unsigned count, uint32_t bitrate, unsigned fd,
                     unsigned *miss, uint16_t *response_10us)
{
    (void)streams;
    (void)bitrate;
    (void)fd;
    *miss = count > 0u ? count - 1u : 0u;
    *response_10us = 0xFFFFu;
    return 0;
}
