/*
 * libups-ecb, private: the state of ups_ecb_elect.c (the election among the CAN-ECBs of a
 * bus). Included by ups_ecb.h; not part of the API.
 */
#ifndef UPS_ECB_ELECT_H
#define UPS_ECB_ELECT_H

#include <stdint.h>

typedef struct {
    uint8_t role; /* UPS_ECB_STOPPED, ... */
    /* to be filled in by ups_ecb_elect.c */
    uint8_t unused;
} ups_ecb_elect_t;

#endif /* UPS_ECB_ELECT_H */
