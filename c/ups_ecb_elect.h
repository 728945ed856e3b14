/*
 * libups-ecb, private: the state of ups_ecb_elect.c (the election among the CAN-ECBs of a
 * bus). Included by ups_ecb.h after its configuration macros; not part of the API.
 */
#ifndef UPS_ECB_ELECT_H
#define UPS_ECB_ELECT_H

#include <stdint.h>

#if UPS_ECB_WATCHED < 1 || UPS_ECB_WATCHED > 1024
#error "UPS_ECB_WATCHED must be 1..1024"
#endif

/** A request watched while standing by (since when it is asked), or the answer to one heard
 *  lately (when), by its key: the joiners' Knocks, or the UID of a binding request. */
typedef struct {
    uint8_t uid[8];   /* big-endian; zero for the Knocks */
    uint16_t t;       /* since when asked, or when answered: the clock's low 16 bits (the
                         entries live seconds: the tick forgets them long before 65 s) */
    uint8_t knock;    /* 1: the key of the Knocks; 0: the UID's */
    uint8_t pad;
} ups_ecb_watch_t;

typedef struct {
    uint8_t role;         /* UPS_ECB_STOPPED, ... */
    uint8_t wary;         /* it caught another not answering: claims alone move it no more */
    uint8_t due;          /* serving: a Serving in answer is owed (sent once the gap passed) */
    uint8_t known;        /* which of t_known[] hold a time (bits, 1 << index) */
    uint16_t candidacy;   /* ms: the recovery time, at most 2 s */
    uint16_t n_asked;     /* entries in asked[] */
    uint16_t n_answered;  /* entries in answered[] */
    uint16_t pad;
    uint32_t t_role;      /* candidate: its Hello; standing by: the last Hello or Serving of
                             another */
    uint32_t t_probe;     /* standing by: the last Probe (or standing by) */
    uint32_t t_serving;   /* serving: the last Serving (the beat counts from it) */
    uint32_t t_known[4];  /* the last Serving in answer to another's frame, the last answer to
                             a node that another sent, serving and wary: the last Serving of a
                             lower instance, the last Hello (ups_ecb_elect.c's KNOWN_...) */
    uint8_t assigned[16]; /* the TxNodes of the Assigns of others, and of the CLAIMs that
                             answered a Hello, heard since its own last Hello (bit t % 8 of byte
                             t / 8): their binding requests are watched */
    /* standing by: the requests heard and not answered yet, oldest first */
    ups_ecb_watch_t asked[UPS_ECB_WATCHED];
    /* the answers heard in the last second (EARLY), oldest first */
    ups_ecb_watch_t answered[UPS_ECB_WATCHED];
} ups_ecb_elect_t;

#endif /* UPS_ECB_ELECT_H */
