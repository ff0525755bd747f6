/* fastpath.h: what the compiled parts of the executor's hot path share.
 *
 * One module, _fastpath, built from one source per job (see module.c for
 * the whole picture): held.c (rclpy handles held and entered), notifier.c
 * (rmw's new-data callbacks), waitset.c (an rcl wait set over fixed
 * entities), taker.c (rcl_take into a kept message), service.c (the same
 * for services and clients, and answers), lock.c (a mutex both languages
 * use), lanes.c (the callback groups' slot state and the objects both
 * languages read: work, tokens, runners, routes), express.c (the loop
 * thread's async chain), watcher.c (asyncio's file descriptors wake the
 * loop's rcl wait), handoff.c (the loop and the workers it wakes: who waits
 * for whom, and who stays awake), meter.c (what each entity's callbacks
 * cost), deadline.c (the process ends at a moment no Python code can be
 * counted on to reach). Every object one file reads of another's is a compiled type
 * declared here: no file reads a Python attribute of the executor's own
 * classes by name. container/executor/_pyengine/ does the same job in Python,
 * module for module, with the same names (_fastpath.pyi describes both).
 *
 * Ownership, the rules every file keeps (and the field notes below say per
 * field who owns what):
 *
 * - An object that reads an rcl or rmw pointer owns the rclpy handle that
 *   owns the memory behind it: a strong reference, entered (__enter__) so
 *   rclpy defers the rcl object's destruction, until the object's close()
 *   or its collection (Held, held.c). The pointer is read from the handle,
 *   never taken as an integer. Addresses leave C only as keys (which entity
 *   is ready), never to be dereferenced.
 * - A field holding a PyObject * holds a strong reference, unless its note
 *   says "borrowed"; none is borrowed across a call into Python (which can
 *   run any code, the garbage collector's included): what is read out of a
 *   mutable container (a list, a dict, a writable member) is held first.
 * - Nothing allocates a Python object while holding a lock that threads
 *   without the GIL take (the Notifier's, which DDS threads take): what is
 *   read under it is copied into C first.
 * - State both languages change has one owner, the compiled object; Python
 *   changes it through that object's methods (Slots' idle runners, its
 *   active work) or its members, and reads containers C was given (asyncio's
 *   ready queue, the dispatcher's eager queue, the completion waiters) only
 *   by their length.
 */
#ifndef CONTAINER_EXECUTOR_FASTPATH_H
#define CONTAINER_EXECUTOR_FASTPATH_H

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <limits.h>
#include <pthread.h>
#include <stdatomic.h>
#include <stdbool.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include <rcl/client.h>
#include <rcl/error_handling.h>
#include <rcl/event.h>
#include <rcl/guard_condition.h>
#include <rcl/publisher.h>
#include <rcl/service.h>
#include <rcl/subscription.h>
#include <rcl/timer.h>
#include <rcl/wait.h>
#include <rmw/error_handling.h>
#include <rmw/rmw.h>
#include <rmw/types.h>

enum { KIND_SUBSCRIPTION = 0, KIND_CLIENT = 1, KIND_SERVICE = 2, KIND_EVENT = 3 };

static inline long long monotonic_ns(void)
{
  struct timespec now;
  clock_gettime(CLOCK_MONOTONIC, &now);
  return (long long)now.tv_sec * 1000000000LL + now.tv_nsec;
}

/* NULL, with RuntimeError "<call> failed: <rcl's error>" set and rcl's error reset. */
static inline PyObject * rcl_failed(const char * call)
{
  PyErr_Format(PyExc_RuntimeError, "%s failed: %s", call, rcl_get_error_string().str);
  rcl_reset_error();
  return NULL;
}

/* The longest a carrier thread's publish may leave the waiter asleep (see
 * on_event), should the publishing callback run on: rclpy's (and rclcpp's)
 * single-threaded executors hold such a message until the callback returns,
 * however long. 2 ms skipped only three quarters of the pointless wake-ups
 * of ten 100 Hz timers (the loop's next firing is often further away); 5 ms
 * skipped all of them.
 *
 * Measured against (commit cf332c8, the project's 2-core shared KVM VM):
 * bench_executor.py's ten-node load with plain callbacks, its loop
 * wake-ups counted (4,700 a second down to 1,050) and the process's CPU
 * in five back-to-back pairs (10.6-18.7% against 18.5-24.1%; docs/design.md,
 * "Not waking the loop for a carried message"); 2 ms and 5 ms are the
 * values recorded. Not a spin: a wake-up skipped. On one CPU it holds as
 * it is (a skipped wake-up spares that CPU a thread switch too); not
 * measured there. */
#define DEFER_MAX_NS 5000000LL

/* Set on lane worker threads that, after every plain callback, take what it
 * published for other plain callbacks themselves (Notifier.carry). */
/* A thread-local of this module: initial-exec, a plain %fs-relative access. The default
 * model for a shared object (general-dynamic) calls __tls_get_addr at every access: 0.65% of
 * the CPU of a round trip between two nodes' asyncio tasks went there, from the meter's three
 * (perf, bench_accounting.py's streams). The module's few bytes fit the static TLS surplus
 * glibc keeps for objects loaded later (dlopen). */
#define THREAD_LOCAL _Thread_local __attribute__((tls_model("initial-exec")))

extern THREAD_LOCAL int carrier_thread;
/* Whether any thread was ever marked: until then no publish can be deferred,
 * and a wait need not work out when it ends (an async-only process). */
extern atomic_int carriers_exist;

/* The event count that means "take until nothing is left". */
#define DRAIN ((size_t)1 << 30)

/* -- held.c ------------------------------------------------------------------ */
/* An rclpy handle held: a strong reference to it, entered (rclpy defers the
 * destruction of the rcl object while it is), and the rcl object's address,
 * read from its ``pointer`` once. NULL handle: nothing held. */
typedef struct {
  PyObject * handle;
  void * pointer;
} Held;

/* Hold and enter handle: 0, or -1 with an exception set (rclpy's
 * InvalidHandle for one destroyed already) and nothing held. */
int held_enter(Held * held, PyObject * handle);
/* Exit and let go (nothing when nothing is held); an exception already set
 * stays set, and one __exit__ raises is reported as unraisable. */
void held_exit(Held * held);
/* The handles in a sequence, held and entered (a new array of count, to be
 * given to held_exit_all): 0, or -1 with an exception and nothing held. */
int held_enter_all(PyObject * sequence, Held ** out, size_t * count);
void held_exit_all(Held ** held, size_t * count);

typedef struct Slot {
  struct NotifierObject * owner; /* borrowed: the notifier frees its slots before itself */
  Held entity;   /* the watched entity's handle (its address is the key reported) */
  uintptr_t key;
  int kind;
  int queued;    /* under owner->lock */
  int plain;     /* its callback runs on a worker thread: carry() hands it out */
  size_t count;  /* events since last ready(), under owner->lock */
  struct Slot * next;
} Slot;

typedef struct NotifierObject {
  PyObject_HEAD
  pthread_mutex_t lock;
  atomic_int armed;
  atomic_int pending;
  atomic_int plain_pending;      /* queued slots that are plain */
  rcl_guard_condition_t * guard; /* under lock; NULL once closed (guard_held still owns it) */
  Held guard_held;               /* the guard condition's handle (Python thread only) */
  Slot * slots;                  /* touched by the owning Python thread only */
  Slot ** ready;                 /* under lock */
  size_t nready;
  size_t capacity;
  atomic_ulong triggers;
  /* While the waiter blocks in WaitSet.wait: when it wakes at the latest
   * (CLOCK_MONOTONIC ns, its timeout or its soonest timer); LLONG_MAX
   * otherwise, or when unknown. */
  atomic_llong wake_by;
} NotifierObject;


/* -- notifier.c ------------------------------------------------------------ */
extern PyTypeObject NotifierType;
/* Trigger the notifier's guard, armed or not (a timer's reset: see waitset.c). */
void notifier_wake(NotifierObject * self);
/* How many reported entities notifier_take_reported moves without allocating. */
#define REPORTED_INLINE 16
Py_ssize_t notifier_take_reported(
  NotifierObject * self, uintptr_t ** keys, size_t ** counts, uintptr_t * inline_keys, size_t * inline_counts);

/* -- watcher.c --------------------------------------------------------------- */
extern PyTypeObject FdWatcherType;

/* -- deadline.c -------------------------------------------------------------- */
extern PyTypeObject DeadlineType;
extern PyTypeObject HandoffType;
typedef struct HandoffObject HandoffObject;
/* On the loop thread, without the GIL: whether workers it woke still run
 * (and lingering has not been failing lately: see handoff.c). */
int handoff_may_linger(HandoffObject * self);
/* Then, before blocking for up to timeout_ns (negative: no limit): stay
 * awake while they run, until an answer woke the armed notifier (armed
 * went to 0); 1 if one did. */
int handoff_loop_linger(HandoffObject * self, const atomic_int * armed, long long timeout_ns);
/* Whether the loop thread is in a wait without the GIL (a lingering worker takes it then). */
void handoff_loop_free(HandoffObject * self, int free);

/* -- waitset.c --------------------------------------------------------------- */
extern PyTypeObject WaitSetType;
long long poll_timeout(long long timeout);

/* -- taker.c ----------------------------------------------------------------- */
typedef void * (*create_message_t)(void);
typedef void (*destroy_message_t)(void *);
typedef PyObject * (*convert_to_py_t)(void *);

/* A message type's rosidl functions, each with the capsule that carries it (held). */
typedef struct {
  PyObject * type;     /* the message type */
  PyObject * capsules; /* tuple of the capsules the pointers below came from */
  create_message_t create;
  destroy_message_t destroy;
  convert_to_py_t to_py;
  bool (*from_py)(PyObject *, void *);
} MessageFunctions;

/* The functions of ``type`` (a message type, or a service type's part
 * ``part`` when not NULL); from_py only when wanted: 0, or -1 with an exception. */
int message_functions(PyObject * type, const char * part, int want_from_py, MessageFunctions * out);
void message_functions_clear(MessageFunctions * functions);

typedef struct {
  PyObject_HEAD
  Held subscription;   /* rcl_subscription_t */
  MessageFunctions functions;
  void * message;      /* owned: made with functions.create, destroyed with functions.destroy */
  int with_gid; /* the message info carries publisher_gid, as rclpy 9's does */
} TakerObject;

extern PyTypeObject TakerType;
PyObject * taker_take(TakerObject * self, int with_info);
PyObject * gid_dict(const rmw_gid_t * gid);

/* -- service.c --------------------------------------------------------------- */
extern PyTypeObject ServerType;
extern PyTypeObject CallerType;

/* -- lock.c ------------------------------------------------------------------ */
typedef struct {
  PyObject_HEAD
  PyThread_type_lock lock;
  int locked;
} LockObject;

extern PyTypeObject LockType;

#define IS_LOCK(object) (Py_TYPE(object) == &LockType)

/* Take the lock without waiting: 1 taken, 0 busy. */
static inline int lock_try(LockObject * self)
{
  if (self->locked || !PyThread_acquire_lock(self->lock, NOWAIT_LOCK)) {
    return 0;
  }
  self->locked = 1;
  return 1;
}

static inline void lock_release(LockObject * self)
{
  self->locked = 0;
  PyThread_release_lock(self->lock);
}

/* -- meter.c ----------------------------------------------------------------- */
#define METER_SUB 8
#define METER_BUCKETS (40 * METER_SUB)

/* Plain fields, no lock: every step begins and ends with the GIL held (on
 * the loop thread or a worker), and take() closes a window with it held. */
typedef struct {
  PyObject_HEAD
  unsigned long long runs, finished, dropped, stuck, late_n, dur_n;
  long long busy_ns, cpu_ns, late_max, dur_max;
  long long step_since; /* when in_step last went from 0 to 1 */
  int in_step;          /* steps running now */
  char stuck_counted;   /* the step running now was counted stuck */
  uint32_t late[METER_BUCKETS];
  uint32_t dur[METER_BUCKETS];
} MeterObject;

extern PyTypeObject MeterType;

/* -- handles.c --------------------------------------------------------------- */
extern PyTypeObject HandleMeterType;
/* Readies the type (its tp_new is object's, known only at run time). */
int handle_meter_ready(void);

extern PyMethodDef meter_functions[];
/* A callback's first step starts (arrived: when its work arrived, 0 unknown): its start (ns). */
long long meter_begin(MeterObject * self, long long arrived);
/* A later step of a suspended callback starts: its start (ns). */
long long meter_resume(MeterObject * self);
/* The step that started at step_start suspended. */
void meter_pause(MeterObject * self, long long step_start);
/* The step that started at step_start ended the callback, whose first step started at started. */
void meter_end(MeterObject * self, long long step_start, long long started);

/* -- lanes.c ----------------------------------------------------------------- */
/* node: set once. retired: written by Python (the dispatcher retires a
 * token), read by C before a first step, both with the GIL held. */
typedef struct {
  PyObject_HEAD
  PyObject * node;
  char retired;
} TokenObject;

/* Set once by its constructor (read-only members to Python), but for the
 * times: arrived (a KeepLast keeping an older one's) and started (its meter's
 * first step), written in C with the GIL held. */
typedef struct {
  PyObject_HEAD
  PyObject * entity;
  PyObject * call;
  PyObject * done;
  PyObject * token; /* a Token, or None */
  PyObject * args;  /* a tuple */
  MeterObject * meter; /* NULL: not metered */
  long long arrived;   /* monotonic ns: taken, or due (a timer) */
  long long started;   /* monotonic ns of its first step's start, 0 before */
  Py_ssize_t depth;
  char is_async;
} WorkObject;

/* A runner's fields are written by Python (the lane, through the members)
 * and by first_step (current), both with the GIL held on the loop thread;
 * every reader holds what it read before calling into Python. */
typedef struct {
  PyObject_HEAD
  PyObject * task;
  PyObject * context;
  PyObject * idle;    /* the future it idles on, or None */
  PyObject * current; /* the work it carries, or None */
} RunnerObject;

/* Its list and dict are its own, changed through its functions only. */
typedef struct {
  PyObject_HEAD
  PyObject * items;    /* list, read from head on */
  PyObject * entities; /* list, parallel to items */
  PyObject * counts;   /* dict: entity address -> items of it */
  Py_ssize_t head;
} KeepLastObject;

/* A lane's state, owned here: Python changes it through the methods only
 * (under lock, or, for the idle runners, on the loop thread), the chain in
 * express.c reads and changes it directly while lock is free. */
typedef struct {
  PyObject_HEAD
  LockObject * lock;
  Py_ssize_t running;
  Py_ssize_t limit;
  Py_ssize_t dropped;
  char closed;
  KeepLastObject * pending;
  PyObject * active;       /* set of Work started and not done (private) */
  PyObject * idle_runners; /* list of parked Runners, the last used first (private) */
} SlotsObject;

/* Set once from Python (read-only members); arrived is express.c's. */
typedef struct {
  PyObject_HEAD
  PyObject * first;  /* a Taker (subscription) or the timer's handle */
  Held timer;        /* a timer's route: its handle, held (NULL handle for a subscription's) */
  PyObject * entry;  /* opaque: handed back to the hooks */
  PyObject * lane;   /* opaque: handed back to the hooks */
  SlotsObject * slots;
  PyObject * marker; /* Work */
  PyObject * entity;
  TokenObject * token;
  PyObject * callback; /* str: the entity's attribute holding its callback */
  long long arrived;   /* when what it runs next arrived (monotonic ns): taken, or the timer's due time */
} RouteObject;

/* dirty and closed: written by Python (dirty by any thread, with the GIL;
 * closed under the wait set's take lock), read by express.c under that lock
 * before each batch it takes. */
typedef struct {
  PyObject_HEAD
  char dirty;
  char closed;
  PyObject * subscriptions; /* dict: address -> Route, a copy of what Python set */
  PyObject * timers;        /* dict: address -> Route, a copy of what Python set */
} RoutesObject;

extern PyTypeObject TokenType, WorkType, RunnerType, KeepLastType, SlotsType, RouteType, RoutesType;

int keeplast_push(KeepLastObject * self, PyObject * item, PyObject * entity, Py_ssize_t depth);
PyObject * keeplast_pop(KeepLastObject * self);
Py_ssize_t keeplast_size(KeepLastObject * self);
int keeplast_clear(KeepLastObject * self);
PyObject * slots_admit_first_step(SlotsObject * self);
int slots_release_first_step(SlotsObject * self);
void slots_undo_first_step(SlotsObject * self);

/* -- express.c --------------------------------------------------------------- */
extern PyTypeObject ExpressType;
/* The module's functions that express.c defines (first_step). */
extern PyMethodDef express_functions[];

#endif
