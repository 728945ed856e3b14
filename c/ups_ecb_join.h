/*
 * libups-ecb, private: the state of ups_ecb_join.c (TxNodes by node id, the census, Offers).
 * Included by ups_ecb.h after its configuration macros; not part of the API.
 */
#ifndef UPS_ECB_JOIN_H
#define UPS_ECB_JOIN_H

#include <stdint.h>

typedef struct {
    uint8_t node_id[8]; /* big-endian */
    uint8_t txnode;     /* 0xFF: unused entry */
    uint8_t pad[3];
    uint32_t t_seen;    /* the last frame of its TxNode */
} ups_ecb_node_t;

typedef struct {
    ups_ecb_node_t nodes[UPS_ECB_NODES];
    /* the census's state: to be filled in by ups_ecb_join.c */
    uint8_t unused;
} ups_ecb_join_t;

#endif /* UPS_ECB_JOIN_H */
