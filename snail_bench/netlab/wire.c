/* The lab's wire in C: delay, jitter and loss on each link, frame by frame.
 *
 * The same forwarder as wire.py (its module doc says why the lab needs one), without
 * Python per frame: frames are read in batches with recvmmsg straight into fixed slots
 * (the slot freed last is reused first, so a short queue keeps touching the same warm
 * pages) and sent in batches with sendmmsg once due, so a 64 KiB GSO frame
 * costs two kernel copies and a share of two system calls. Profiled with the Python wire
 * on a zero-delay lab: about half of its CPU per invocation was the interpreter.
 *
 * Usage: wire --link A_IF,B_IF,DELAY_MS,JITTER_MS,LOSS_PCT [--link ...]
 * Prints "ready" once every socket is bound; runs until SIGTERM or SIGINT. Each direction
 * is a FIFO whose departures never go backwards (jitter delays, never reorders); loss
 * drops a frame before it is queued; a full queue leaves frames in the socket's buffer,
 * which drops what overflows, as a router's queue would. Built by wire_native.py on
 * first use, with the system's C compiler.
 */
#define _GNU_SOURCE
#include <arpa/inet.h>
#include <errno.h>
#include <linux/if_packet.h>
#include <net/ethernet.h>
#include <net/if.h>
#include <poll.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#define FRAME_MAX (65536 + 64) /* a GSO frame and its virtio-net header */
#define SLOTS 4096             /* frames queued per direction (256 MiB of address space) */
#define BURST 64               /* frames per recvmmsg or sendmmsg */
#define MAX_LINKS 8
#define SOCKET_BUFFER (8 << 20)
#ifndef PACKET_VNET_HDR
#define PACKET_VNET_HDR 15
#endif
#ifndef PACKET_IGNORE_OUTGOING
#define PACKET_IGNORE_OUTGOING 23
#endif

struct direction {
    int in, out;               /* read from in, write to out */
    int64_t delay_ns, jitter_ns;
    uint32_t loss;             /* drop when a 32-bit random draw is below this */
    unsigned char *slots;      /* SLOTS x FRAME_MAX, mapped lazily */
    uint32_t len[SLOTS];       /* by slot */
    uint32_t queue[SLOTS];     /* slots in departure order, [head, tail) */
    int64_t due[SLOTS];        /* by queue position */
    uint64_t head, tail;
    uint32_t free[SLOTS];      /* a stack: the slot freed last is reused first, so the */
    uint32_t n_free;           /* pages a queue touches stay few and warm */
    int64_t last_due;
};

static unsigned char *slot_data(struct direction *d, uint32_t slot) {
    return d->slots + (size_t)slot * FRAME_MAX;
}

static volatile sig_atomic_t stop;
static uint64_t rng_state;

static void on_signal(int sig) { (void)sig; stop = 1; }

static int64_t now_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

static uint64_t next_random(void) { /* xorshift64*: jitter and loss, not secrets */
    rng_state ^= rng_state >> 12;
    rng_state ^= rng_state << 25;
    rng_state ^= rng_state >> 27;
    return rng_state * 0x2545F4914F6CDD1DULL;
}

static int packet_socket(const char *ifname) {
    int fd = socket(AF_PACKET, SOCK_RAW | SOCK_NONBLOCK, htons(ETH_P_ALL));
    int one = 1, size = SOCKET_BUFFER;
    struct sockaddr_ll addr = {0};
    if (fd < 0) return -1;
    if (setsockopt(fd, SOL_PACKET, PACKET_VNET_HDR, &one, sizeof one) < 0 ||
        setsockopt(fd, SOL_PACKET, PACKET_IGNORE_OUTGOING, &one, sizeof one) < 0 ||
        setsockopt(fd, SOL_SOCKET, SO_RCVBUFFORCE, &size, sizeof size) < 0 ||
        setsockopt(fd, SOL_SOCKET, SO_SNDBUFFORCE, &size, sizeof size) < 0)
        return -1;
    addr.sll_family = AF_PACKET;
    addr.sll_protocol = htons(ETH_P_ALL);
    addr.sll_ifindex = (int)if_nametoindex(ifname);
    if (addr.sll_ifindex == 0 || bind(fd, (struct sockaddr *)&addr, sizeof addr) < 0)
        return -1;
    return fd;
}

/* Read what the socket has (up to the free slots) and queue it with its due time. */
static void admit(struct direction *d, int64_t now) {
    struct mmsghdr msgs[BURST];
    struct iovec iov[BURST];
    for (;;) {
        int want = d->n_free < BURST ? (int)d->n_free : BURST, got, i;
        if (want == 0) return;
        for (i = 0; i < want; i++) {
            iov[i].iov_base = slot_data(d, d->free[d->n_free - 1 - i]);
            iov[i].iov_len = FRAME_MAX;
            memset(&msgs[i], 0, sizeof msgs[i]);
            msgs[i].msg_hdr.msg_iov = &iov[i];
            msgs[i].msg_hdr.msg_iovlen = 1;
        }
        got = recvmmsg(d->in, msgs, (unsigned)want, MSG_DONTWAIT, NULL);
        if (got <= 0) return;
        uint32_t taken[BURST];
        for (i = 0; i < got; i++)
            taken[i] = d->free[--d->n_free];
        for (i = 0; i < got; i++) {
            int64_t due = now + d->delay_ns;
            if (d->loss && (uint32_t)(next_random() >> 32) < d->loss) {
                d->free[d->n_free++] = taken[i];
                continue;
            }
            if (d->jitter_ns)
                due += (int64_t)(next_random() % (uint64_t)(2 * d->jitter_ns + 1)) -
                       d->jitter_ns;
            if (due < d->last_due) due = d->last_due;
            d->last_due = due;
            d->len[taken[i]] = msgs[i].msg_len;
            d->queue[d->tail % SLOTS] = taken[i];
            d->due[d->tail % SLOTS] = due;
            d->tail++;
        }
        if (got < want) return;
    }
}

/* Send every due frame; returns the next departure time, 0 if none is queued, or a
 * time shortly ahead when the device's queue is full. */
static int64_t flush(struct direction *d, int64_t now) {
    struct mmsghdr msgs[BURST];
    struct iovec iov[BURST];
    while (d->head < d->tail) {
        int n = 0, sent, i;
        while (n < BURST && d->head + n < d->tail && d->due[(d->head + n) % SLOTS] <= now) {
            uint32_t slot = d->queue[(d->head + n) % SLOTS];
            iov[n].iov_base = slot_data(d, slot);
            iov[n].iov_len = d->len[slot];
            memset(&msgs[n], 0, sizeof msgs[n]);
            msgs[n].msg_hdr.msg_iov = &iov[n];
            msgs[n].msg_hdr.msg_iovlen = 1;
            n++;
        }
        if (n == 0) return d->due[d->head % SLOTS];
        sent = sendmmsg(d->out, msgs, (unsigned)n, MSG_DONTWAIT);
        if (sent < 0) {
            if (errno == EAGAIN || errno == ENOBUFS) return now + 200000;
            sent = 1; /* a frame the device refuses is lost, as on a wire */
        }
        for (i = 0; i < sent; i++)
            d->free[d->n_free++] = d->queue[(d->head + i) % SLOTS];
        d->head += (uint64_t)sent;
    }
    return 0;
}

static int parse_link(char *text, char **a, char **b, double v[3]) {
    char *parts[5];
    int i;
    for (i = 0; i < 5; i++) {
        parts[i] = strsep(&text, ",");
        if (parts[i] == NULL) return -1;
    }
    if (text != NULL) return -1;
    *a = parts[0];
    *b = parts[1];
    for (i = 0; i < 3; i++) {
        char *end;
        v[i] = strtod(parts[2 + i], &end);
        if (*end != '\0' || v[i] < 0) return -1;
    }
    return 0;
}

int main(int argc, char **argv) {
    static struct direction dirs[2 * MAX_LINKS];
    struct pollfd fds[2 * MAX_LINKS];
    int n_dirs = 0, i;
    struct sigaction sa = {0};

    rng_state = (uint64_t)now_ns() ^ ((uint64_t)getpid() << 32) ^ 0x9E3779B97F4A7C15ULL;
    for (i = 1; i < argc; i++) {
        char *a, *b;
        double v[3];
        int sa_fd, sb_fd, k;
        if (strcmp(argv[i], "--link") != 0 || i + 1 >= argc || n_dirs >= 2 * MAX_LINKS ||
            parse_link(argv[++i], &a, &b, v) != 0) {
            fprintf(stderr, "wire: usage: --link A_IF,B_IF,DELAY_MS,JITTER_MS,LOSS_PCT ...\n");
            return 2;
        }
        sa_fd = packet_socket(a);
        sb_fd = packet_socket(b);
        if (sa_fd < 0 || sb_fd < 0) {
            fprintf(stderr, "wire: cannot open %s or %s: %s\n", a, b, strerror(errno));
            return 1;
        }
        for (k = 0; k < 2; k++) {
            struct direction *d = &dirs[n_dirs++];
            d->in = k ? sb_fd : sa_fd;
            d->out = k ? sa_fd : sb_fd;
            d->delay_ns = (int64_t)(v[0] * 1e6);
            d->jitter_ns = (int64_t)(v[1] * 1e6);
            d->loss = v[2] >= 100 ? UINT32_MAX : (uint32_t)(v[2] / 100 * 4294967296.0);
            d->slots = mmap(NULL, (size_t)SLOTS * FRAME_MAX, PROT_READ | PROT_WRITE,
                            MAP_PRIVATE | MAP_ANONYMOUS | MAP_NORESERVE, -1, 0);
            if (d->slots == MAP_FAILED) {
                fprintf(stderr, "wire: no memory for the queues\n");
                return 1;
            }
            for (d->n_free = 0; d->n_free < SLOTS; d->n_free++)
                d->free[d->n_free] = SLOTS - 1 - d->n_free; /* slot 0 on top */
        }
    }
    if (n_dirs == 0) {
        fprintf(stderr, "wire: no --link given\n");
        return 2;
    }
    sa.sa_handler = on_signal;
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    printf("ready\n");
    fflush(stdout);
    while (!stop) {
        int64_t now = now_ns(), next = 0, wait = -1;
        struct timespec ts;
        for (i = 0; i < n_dirs; i++) {
            int64_t due = flush(&dirs[i], now);
            if (due && (next == 0 || due < next)) next = due;
        }
        if (next) {
            wait = next - now_ns();
            if (wait < 0) wait = 0;
            ts.tv_sec = wait / 1000000000;
            ts.tv_nsec = wait % 1000000000;
        }
        for (i = 0; i < n_dirs; i++) {
            fds[i].fd = dirs[i].in;
            /* a full ring reads nothing more until it drains */
            fds[i].events = dirs[i].n_free ? POLLIN : 0;
            fds[i].revents = 0;
        }
        /* wait == 0: a frame is due now, but take in what has arrived meanwhile too */
        if (ppoll(fds, (nfds_t)n_dirs, wait < 0 ? NULL : &ts, NULL) < 0 && errno != EINTR) {
            perror("wire: poll");
            return 1;
        }
        now = now_ns();
        for (i = 0; i < n_dirs; i++)
            if (fds[i].revents & POLLIN)
                admit(&dirs[i], now);
    }
    return 0;
}
