/*
 * What a host program (the Python binding in ups/_cnode.py) needs to know of the library as it
 * was compiled: the size of ups_node_t and the configuration macros. Not for firmware.
 */
#include "../ups.h"

/** sizeof(ups_node_t), so that the caller can place one. */
size_t ups_host_node_size(void);
/** The configuration: 0 channels, 1 TX depth, 2 transfers, 3 FD, 4 largest event, 5 receive
 *  slots, 6 declarations, 7 heard Binds, 8 bytes per counter, 9 frame data bytes; else -1. */
long ups_host_config(int what);

size_t ups_host_node_size(void)
{
    return sizeof(ups_node_t);
}

long ups_host_config(int what)
{
    switch (what) {
    case 0: return UPS_CHANNELS;
    case 1: return UPS_TX_DEPTH;
    case 2: return UPS_WITH_TRANSFERS;
    case 3: return UPS_WITH_FD;
    case 4: return UPS_MAX_EVENT;
    case 5: return UPS_RX_TRANSFERS;
    case 6: return UPS_DECLARATIONS;
    case 7: return UPS_HEARD_BINDS;
    case 8: return (long)sizeof(UPS_COUNTER_T);
    case 9: return UPS_MTU;
    default: return -1;
    }
}
