/*
 * libups-ecb, private: the state of ups_ecb_bind.c (etags by UID, who uses them, quotas, held
 * requests, rosters, declared streams). Included by ups_ecb.h; not part of the API.
 */
#ifndef UPS_ECB_BIND_H
#define UPS_ECB_BIND_H

#include <stdint.h>

typedef struct {
    uint8_t uid[8];   /* big-endian */
    uint16_t etag;    /* 0: unused entry */
    uint8_t creator;  /* the node entry (ups_ecb_join_t.nodes) that created it; 0xFF: nobody */
    uint8_t pad;
} ups_ecb_channel_t;

typedef struct {
    ups_ecb_channel_t channels[UPS_ECB_CHANNELS];
    /* to be filled in by ups_ecb_bind.c */
    uint8_t unused;
} ups_ecb_bind_t;

#endif /* UPS_ECB_BIND_H */
