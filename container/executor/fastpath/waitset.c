/* WaitSet: an rcl wait set over fixed entities, filled, waited on and read in one call (see module.c).
 *
 * Timers: only those due next go into the rcl wait set. rcl_wait walks
 * every timer it is given (each one's next deadline, a clock read, a ROS
 * time override check) and Fast DDS attaches and detaches each timer's guard
 * condition, on every wait: with 500 nodes' timers that walk was over half
 * of the process's CPU (perf, bench_scale.py's 500-node async process),
 * and the cost per callback grew with the node count. Here the timers wait
 * in a min-heap of their deadlines (CLOCK_MONOTONIC ns, from rcl's own
 * time until the next call), and each wait adds to the rcl wait set only
 * those due within HEAP_SLACK_NS of the soonest (or now), which rcl then
 * times exactly as before. A timer so added is read again at the next wait
 * (called by then, or not: then it is due still) and goes back to the heap.
 *
 * What rcl told apart by waiting on every timer, told apart here:
 * - A reset moves a deadline later (never earlier: now + period), or
 *   restarts a cancelled timer. A deadline later than the heap's wakes the
 *   wait early once, finds the timer not due and puts it back. Cancelled
 *   timers wait apart, and are read again only after some timer was reset:
 *   every timer's on-reset callback counts resets (timer_resets), and wakes
 *   each wait set that has cancelled timers through its notifier's guard,
 *   as rcl's reset woke a wait through the timer's own guard condition.
 *   Without a notifier (nothing to wake), cancelled timers stay in every
 *   wait, as in rcl.
 * - A ROS-time timer whose clock's ROS time override is on (simulated
 *   time) is woken by its clock's jumps, through its guard condition: it
 *   goes into every wait, as in rcl. A timer whose override is switched on
 *   while it waits in the heap is found so at its system-time deadline,
 *   one period late at most.
 */
#include "fastpath.h"

/* ------------------------------------------------------------------------ */
enum { WS_SUBSCRIPTIONS, WS_GUARDS, WS_TIMERS, WS_CLIENTS, WS_SERVICES, WS_EVENTS, WS_KINDS };

/* Timers due within this much of the soonest go into the same wait: one
 * wake-up for timers whose deadlines are that close, as rcl's wait gave. */
#define HEAP_SLACK_NS 1000000LL

/* One timer in the heap: its deadline, and its index among the wait set's timers. */
typedef struct {
  long long due;
  size_t index;
} TimerDue;

/* The timers of one wait set, by where each waits (each index in one place). */
typedef struct {
  TimerDue * heap;    /* by deadline */
  size_t heap_n;
  size_t * armed;     /* in the rcl wait set of the last wait: read again at the next */
  size_t armed_n;
  size_t * always;    /* ROS time overridden (or unreadable): in every wait, read again at each */
  size_t always_n;
  size_t * cancelled; /* read again once some timer was reset */
  size_t cancelled_n;
  unsigned long resets_seen; /* timer_resets when cancelled was last read */
  long long soonest;         /* the earliest deadline among armed (LLONG_MAX: none) */
} Timers;

typedef struct WaitSetObject WaitSetObject;

struct WaitSetObject {
  PyObject_HEAD
  rcl_wait_set_t wait_set;
  int initialised;
  int waiting;                 /* a thread is in rcl_wait without the GIL: close() must not free under it */
  Held context;                /* rcl_context_t the wait set was made in */
  Held * entities[WS_KINDS];   /* each kind's handles, held (what the wait set points at) */
  size_t counts[WS_KINDS];
  NotifierObject * notifier; /* told when each wait ends at the latest, or NULL */
  HandoffObject * handoff;   /* the loop's hand-overs to workers (with a notifier only), or NULL */
  Timers timers;             /* touched by the thread in wait() only (one at a time) */
  size_t timers_waited;      /* how many timers the last wait gave rcl_wait */
  int registered;            /* in the list that timer resets wake (see on_timer_reset) */
  WaitSetObject * next_registered;
};

/* -- timer resets ------------------------------------------------------------ */
/* Resets of any timer a wait set was given, and the wait sets (with a
 * notifier and timers) that a reset wakes: registered at init, let go at
 * close, under reset_lock, which the callback holds while it wakes them. */
static atomic_ulong timer_resets = 0;
static pthread_mutex_t reset_lock = PTHREAD_MUTEX_INITIALIZER;
static WaitSetObject * reset_waiters = NULL;

/* rcl's on-reset callback of every timer given to a wait set, from
 * whichever thread resets it (the GIL may not be held). No user data: it
 * stays valid after its wait set is gone (a later wait set sets it again). */
static void on_timer_reset(const void * Py_UNUSED(user_data), size_t Py_UNUSED(count))
{
  WaitSetObject * waiter;
  atomic_fetch_add(&timer_resets, 1);
  pthread_mutex_lock(&reset_lock);
  /* Every one: which of them has cancelled timers is their waiting thread's to know. Resets are few. */
  for (waiter = reset_waiters; waiter != NULL; waiter = waiter->next_registered) {
    notifier_wake(waiter->notifier);
  }
  pthread_mutex_unlock(&reset_lock);
}

static void register_for_resets(WaitSetObject * self)
{
  pthread_mutex_lock(&reset_lock);
  self->next_registered = reset_waiters;
  reset_waiters = self;
  self->registered = 1;
  pthread_mutex_unlock(&reset_lock);
}

static void unregister_for_resets(WaitSetObject * self)
{
  WaitSetObject ** link;
  if (!self->registered) {
    return;
  }
  pthread_mutex_lock(&reset_lock);
  for (link = &reset_waiters; *link != NULL; link = &(*link)->next_registered) {
    if (*link == self) {
      *link = self->next_registered;
      break;
    }
  }
  self->registered = 0;
  pthread_mutex_unlock(&reset_lock);
}

/* -- the timer heap ------------------------------------------------------------ */
static void heap_push(Timers * timers, long long due, size_t index)
{
  size_t at = timers->heap_n++;
  while (at > 0) {
    size_t parent = (at - 1) / 2;
    if (timers->heap[parent].due <= due) {
      break;
    }
    timers->heap[at] = timers->heap[parent];
    at = parent;
  }
  timers->heap[at].due = due;
  timers->heap[at].index = index;
}

static TimerDue heap_pop(Timers * timers)
{
  TimerDue top = timers->heap[0];
  TimerDue last = timers->heap[--timers->heap_n];
  size_t at = 0, n = timers->heap_n;
  for (;;) {
    size_t child = 2 * at + 1;
    if (child >= n) {
      break;
    }
    if (child + 1 < n && timers->heap[child + 1].due < timers->heap[child].due) {
      ++child;
    }
    if (last.due <= timers->heap[child].due) {
      break;
    }
    timers->heap[at] = timers->heap[child];
    at = child;
  }
  if (n > 0) {
    timers->heap[at] = last;
  }
  return top;
}

enum { TIMER_DUE, TIMER_CANCELLED, TIMER_ALWAYS };

/* Where timer ``index`` waits now: TIMER_DUE with its deadline in *due,
 * cancelled, or in every wait (ROS time overridden; or unreadable: rcl_wait
 * reports the error as before). */
static int timer_state(WaitSetObject * self, size_t index, long long now, long long * due)
{
  const rcl_timer_t * timer = self->entities[WS_TIMERS][index].pointer;
  rcl_clock_t * clock = NULL;
  int64_t until = 0;
  rcl_ret_t ret = rcl_timer_clock((rcl_timer_t *)timer, &clock);
  if (ret == RCL_RET_OK && clock->type == RCL_ROS_TIME) {
    bool overridden = false;
    ret = rcl_is_enabled_ros_time_override(clock, &overridden);
    if (ret == RCL_RET_OK && overridden) {
      return TIMER_ALWAYS;
    }
  }
  if (ret == RCL_RET_OK) {
    ret = rcl_timer_get_time_until_next_call(timer, &until);
  }
  if (ret == RCL_RET_TIMER_CANCELED) {
    rcl_reset_error();
    /* Without a notifier no reset wakes a wait: it waits in every one, as in rcl. */
    return self->notifier != NULL ? TIMER_CANCELLED : TIMER_ALWAYS;
  }
  if (ret != RCL_RET_OK) {
    rcl_reset_error();
    return TIMER_ALWAYS;
  }
  *due = now + until;
  return TIMER_DUE;
}

/* Put timer ``index`` where it waits now (back into the heap, or apart). */
static void timer_place(WaitSetObject * self, size_t index, long long now)
{
  Timers * timers = &self->timers;
  long long due = 0;
  switch (timer_state(self, index, now, &due)) {
    case TIMER_DUE:
      heap_push(timers, due, index);
      break;
    case TIMER_CANCELLED:
      timers->cancelled[timers->cancelled_n++] = index;
      break;
    default:
      timers->always[timers->always_n++] = index;
      break;
  }
}

/* Choose the timers of the next wait (self->timers.armed): the last wait's
 * read again, the cancelled ones too after a reset, and those the heap has
 * due first. */
static void timers_choose(WaitSetObject * self)
{
  Timers * timers = &self->timers;
  long long now = monotonic_ns(), horizon = 0;
  int have_horizon = 0;
  size_t i, n;
  unsigned long resets = atomic_load(&timer_resets);
  timers->soonest = LLONG_MAX;
  n = timers->armed_n;
  timers->armed_n = 0;
  for (i = 0; i < n; ++i) {
    timer_place(self, timers->armed[i], now);
  }
  n = timers->always_n;
  timers->always_n = 0;
  for (i = 0; i < n; ++i) {
    timer_place(self, timers->always[i], now);
  }
  if (resets != timers->resets_seen) {
    timers->resets_seen = resets;
    n = timers->cancelled_n;
    timers->cancelled_n = 0;
    for (i = 0; i < n; ++i) {
      timer_place(self, timers->cancelled[i], now);
    }
  }
  /* The soonest, and those due within HEAP_SLACK_NS of it. A deadline read
   * again that moved (a reset since) goes back, at its place. */
  while (timers->heap_n > 0 && (!have_horizon || timers->heap[0].due <= horizon)) {
    TimerDue top = heap_pop(timers);
    long long due = 0;
    switch (timer_state(self, top.index, now, &due)) {
      case TIMER_DUE:
        if (due > top.due && (!have_horizon || due > horizon)) {
          heap_push(timers, due, top.index);
          continue;
        }
        timers->armed[timers->armed_n++] = top.index;
        if (due < timers->soonest) {
          timers->soonest = due;
        }
        if (!have_horizon) {
          horizon = (due > now ? due : now) + HEAP_SLACK_NS;
          have_horizon = 1;
        }
        break;
      case TIMER_CANCELLED:
        timers->cancelled[timers->cancelled_n++] = top.index;
        break;
      default:
        timers->always[timers->always_n++] = top.index;
        break;
    }
  }
}

static void waitset_close(WaitSetObject * self);

/* Every timer starts as read at the next wait; each gets the on-reset callback. */
static int timers_init(WaitSetObject * self)
{
  Timers * timers = &self->timers;
  size_t count = self->counts[WS_TIMERS], i;
  timers->soonest = LLONG_MAX;
  if (count == 0) {
    return 0;
  }
  timers->heap = PyMem_RawCalloc(count, sizeof(TimerDue));
  timers->armed = PyMem_RawCalloc(count, sizeof(size_t));
  timers->always = PyMem_RawCalloc(count, sizeof(size_t));
  timers->cancelled = PyMem_RawCalloc(count, sizeof(size_t));
  if (timers->heap == NULL || timers->armed == NULL || timers->always == NULL || timers->cancelled == NULL) {
    PyErr_NoMemory();
    return -1;
  }
  for (i = 0; i < count; ++i) {
    timers->armed[timers->armed_n++] = i;
    if (rcl_timer_set_on_reset_callback(self->entities[WS_TIMERS][i].pointer, on_timer_reset, NULL) != RCL_RET_OK) {
      rcl_failed("rcl_timer_set_on_reset_callback");
      return -1;
    }
  }
  timers->resets_seen = atomic_load(&timer_resets);
  if (self->notifier != NULL) {
    register_for_resets(self);
  }
  return 0;
}

static void timers_free(Timers * timers)
{
  PyMem_RawFree(timers->heap);
  PyMem_RawFree(timers->armed);
  PyMem_RawFree(timers->always);
  PyMem_RawFree(timers->cancelled);
  memset(timers, 0, sizeof(*timers));
  timers->soonest = LLONG_MAX;
}

static int WaitSet_init(WaitSetObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {
    "context", "subscriptions", "guard_conditions", "timers", "clients", "services", "events", "notifier",
    "handoff", NULL};
  PyObject * context;
  PyObject * notifier = Py_None;
  PyObject * handoff = Py_None;
  PyObject * given[WS_KINDS] = {NULL, NULL, NULL, NULL, NULL, NULL};
  PyObject * empty;
  rcl_ret_t ret;
  int kind;
  if (self->initialised || self->context.handle != NULL) {
    PyErr_SetString(PyExc_RuntimeError, "WaitSet is initialised once");
    return -1;
  }
  if (!PyArg_ParseTupleAndKeywords(
      args, kwargs, "O|$OOOOOOOO", keywords, &context, &given[WS_SUBSCRIPTIONS], &given[WS_GUARDS],
      &given[WS_TIMERS], &given[WS_CLIENTS], &given[WS_SERVICES], &given[WS_EVENTS], &notifier, &handoff))
  {
    return -1;
  }
  if (notifier != Py_None && !PyObject_TypeCheck(notifier, &NotifierType)) {
    PyErr_SetString(PyExc_TypeError, "notifier must be a Notifier or None");
    return -1;
  }
  if (handoff != Py_None && !PyObject_TypeCheck(handoff, &HandoffType)) {
    PyErr_SetString(PyExc_TypeError, "handoff must be a Handoff or None");
    return -1;
  }
  empty = PyTuple_New(0);
  if (empty == NULL || held_enter(&self->context, context) < 0) {
    Py_XDECREF(empty);
    return -1;
  }
  for (kind = 0; kind < WS_KINDS; ++kind) {
    if (held_enter_all(given[kind] != NULL ? given[kind] : empty, &self->entities[kind], &self->counts[kind]) < 0) {
      while (--kind >= 0) {
        held_exit_all(&self->entities[kind], &self->counts[kind]);
      }
      held_exit(&self->context);
      Py_DECREF(empty);
      return -1;
    }
  }
  Py_DECREF(empty);
  self->wait_set = rcl_get_zero_initialized_wait_set();
  ret = rcl_wait_set_init(
    &self->wait_set, self->counts[WS_SUBSCRIPTIONS], self->counts[WS_GUARDS], self->counts[WS_TIMERS],
    self->counts[WS_CLIENTS], self->counts[WS_SERVICES], self->counts[WS_EVENTS],
    (rcl_context_t *)self->context.pointer, rcl_get_default_allocator());
  if (ret != RCL_RET_OK) {
    rcl_failed("rcl_wait_set_init");
    for (kind = WS_KINDS - 1; kind >= 0; --kind) {
      held_exit_all(&self->entities[kind], &self->counts[kind]);
    }
    held_exit(&self->context);
    return -1;
  }
  if (notifier != Py_None) {
    self->notifier = (NotifierObject *)Py_NewRef(notifier);
    if (handoff != Py_None) {
      self->handoff = (HandoffObject *)Py_NewRef(handoff);
    }
  }
  self->initialised = 1;
  if (timers_init(self) < 0) {
    waitset_close(self);
    return -1;
  }
  return 0;
}

/* The rcl wait set goes (it points at the entities), then the handles, the context last. */
static void waitset_close(WaitSetObject * self)
{
  int kind;
  unregister_for_resets(self);
  timers_free(&self->timers);
  if (self->initialised) {
    self->initialised = 0;
    if (rcl_wait_set_fini(&self->wait_set) != RCL_RET_OK) {
      rcl_reset_error();
    }
  }
  for (kind = WS_KINDS - 1; kind >= 0; --kind) {
    held_exit_all(&self->entities[kind], &self->counts[kind]);
  }
  held_exit(&self->context);
}

static void WaitSet_dealloc(WaitSetObject * self)
{
  waitset_close(self);
  Py_XDECREF(self->notifier);
  Py_XDECREF(self->handoff);
  Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyObject * WaitSet_close(WaitSetObject * self, PyObject * Py_UNUSED(ignored))
{
  if (self->waiting) {
    PyErr_SetString(PyExc_RuntimeError, "WaitSet.close() while a thread waits in it: wake it first");
    return NULL;
  }
  waitset_close(self);
  Py_RETURN_NONE;
}

static rcl_ret_t fill(WaitSetObject * self)
{
  rcl_wait_set_t * ws = &self->wait_set;
  rcl_ret_t ret = rcl_wait_set_clear(ws);
  size_t i;
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_SUBSCRIPTIONS]; ++i) {
    ret = rcl_wait_set_add_subscription(ws, self->entities[WS_SUBSCRIPTIONS][i].pointer, NULL);
  }
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_GUARDS]; ++i) {
    ret = rcl_wait_set_add_guard_condition(ws, self->entities[WS_GUARDS][i].pointer, NULL);
  }
  if (self->counts[WS_TIMERS] > 0) {
    Timers * timers = &self->timers;
    timers_choose(self);
    for (i = 0; ret == RCL_RET_OK && i < timers->armed_n; ++i) {
      ret = rcl_wait_set_add_timer(ws, self->entities[WS_TIMERS][timers->armed[i]].pointer, NULL);
    }
    /* Read again at the next wait as well (their override, their errors). */
    for (i = 0; ret == RCL_RET_OK && i < timers->always_n; ++i) {
      ret = rcl_wait_set_add_timer(ws, self->entities[WS_TIMERS][timers->always[i]].pointer, NULL);
    }
    self->timers_waited = timers->armed_n + timers->always_n;
    if (self->notifier == NULL) {
      for (i = 0; ret == RCL_RET_OK && i < timers->cancelled_n; ++i) {
        ret = rcl_wait_set_add_timer(ws, self->entities[WS_TIMERS][timers->cancelled[i]].pointer, NULL);
      }
      self->timers_waited += timers->cancelled_n;
    }
  }
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_CLIENTS]; ++i) {
    ret = rcl_wait_set_add_client(ws, self->entities[WS_CLIENTS][i].pointer, NULL);
  }
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_SERVICES]; ++i) {
    ret = rcl_wait_set_add_service(ws, self->entities[WS_SERVICES][i].pointer, NULL);
  }
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_EVENTS]; ++i) {
    ret = rcl_wait_set_add_event(ws, self->entities[WS_EVENTS][i].pointer, NULL);
  }
  return ret;
}

/* The ready entities of one kind, as a list of addresses. */
static PyObject * ready_of(const void * const * slots, size_t count)
{
  PyObject * list = PyList_New(0);
  size_t i;
  if (list == NULL) {
    return NULL;
  }
  for (i = 0; i < count; ++i) {
    if (slots[i] != NULL) {
      PyObject * address = PyLong_FromUnsignedLongLong((unsigned long long)(uintptr_t)slots[i]);
      if (address == NULL || PyList_Append(list, address) < 0) {
        Py_XDECREF(address);
        Py_DECREF(list);
        return NULL;
      }
      Py_DECREF(address);
    }
  }
  return list;
}

/* When an rcl_wait with this timeout (ns, negative: none) returns at the
 * latest, on CLOCK_MONOTONIC: rcl_wait's own rule (the timeout or the soonest
 * timer, skipping cancelled timers and ROS-time timers under a time
 * override, which only their clock's jumps wake). The soonest timer's
 * deadline is the one timers_choose read for this wait (the timers it gave
 * rcl_wait are the soonest; the others are later, cancelled, or overridden). */
static long long wake_deadline(WaitSetObject * self, long long timeout)
{
  long long now = monotonic_ns();
  long long by = timeout >= 0 ? now + timeout : LLONG_MAX;
  long long soonest = self->timers.soonest;
  if (soonest < by) {
    by = soonest > now ? soonest : now;
  }
  return by;
}

/* The longest a poll may hold the GIL in rcl_wait, should its guard
 * condition not be in the wait set after all (destroyed at shutdown).
 *
 * A safety bound (commit 1dbf0f2, tested both ways in test_fastpath.py),
 * not a tuned figure: no measurement of the value is recorded. A poll
 * returns at once on its triggered guard; only a missing guard makes it
 * wait, asleep in rcl_wait (not spinning), holding the GIL 1 ms at most:
 * the same on one CPU as on two. */
#define POLL_HOLD_MAX_NS 1000000LL

long long poll_timeout(long long timeout)
{
  return timeout < 0 || timeout > POLL_HOLD_MAX_NS ? POLL_HOLD_MAX_NS : timeout;
}

/* wait(timeout_ns, poll=False). A poll (a wait whose guard condition is
 * already triggered, so rcl_wait returns at once) keeps the GIL. Released
 * for those few microseconds, once a millisecond while a chain of callbacks
 * runs, it wakes a thread waiting for it (a lane's worker, the watchdog),
 * which loses the race to take it back and starts its wait for a forced
 * switch (sys.getswitchinterval()) all over again: a plain 20 Hz timer beside
 * a busy chain ran 0-12 times in 4 s instead of 80. Kept, the waiting
 * thread's switch interval runs out and CPython hands the GIL over. A poll
 * waits at most POLL_HOLD_MAX_NS, whatever its timeout. */
static PyObject * WaitSet_wait(WaitSetObject * self, PyObject * const * args, Py_ssize_t nargs)
{
  long long timeout;
  int poll = 0;
  rcl_wait_set_t * ws = &self->wait_set;
  rcl_ret_t ret;
  if (nargs < 1 || nargs > 2) {
    PyErr_SetString(PyExc_TypeError, "wait(timeout_ns, poll=False)");
    return NULL;
  }
  timeout = PyLong_AsLongLong(args[0]);
  if (timeout == -1 && PyErr_Occurred()) {
    return NULL;
  }
  if (nargs == 2 && (poll = PyObject_IsTrue(args[1])) < 0) {
    return NULL;
  }
  if (!self->initialised) {
    PyErr_SetString(PyExc_RuntimeError, "WaitSet not initialised, or closed");
    return NULL;
  }
  ret = fill(self);
  if (ret == RCL_RET_OK && poll) {
    ret = rcl_wait(ws, (int64_t)poll_timeout(timeout));
  } else if (ret == RCL_RET_OK) {
    /* Only a carrier's publish reads it (on_event). */
    NotifierObject * told = atomic_load(&carriers_exist) ? self->notifier : NULL;
    HandoffObject * handoff = self->handoff;
    /* Set while this thread still holds the GIL: released, it wakes a worker
     * waiting for it, which with one CPU runs at once and publishes before
     * this thread's next line; wake_by unset, that publish woke the loop (a
     * trigger for every other message of a 2 ms timer, seen under CI's
     * pinned legs). A carrier's publish wakes no one while lingering either. */
    long long by = told != NULL ? wake_deadline(self, timeout) : LLONG_MAX;
    if (told != NULL) {
      atomic_store(&told->wake_by, by);
    }
    self->waiting = 1;
    Py_BEGIN_ALLOW_THREADS
    /* Plain work was handed to workers and runs: its answer (a response, a
     * message) usually comes within microseconds, and waking this thread's
     * idle core for it costs more. So the thread stays awake for it first,
     * no later than the wait would end (its timeout, its soonest timer): no
     * timer fires later for it. An answer that comes disarmed the notifier
     * and triggered its guard: rcl_wait then returns at once. Never with
     * one CPU (the Handoff's spin is off: see handoff.c), where the worker
     * could only answer once this thread stopped spinning. */
    int linger = handoff != NULL && timeout != 0 && handoff_may_linger(handoff);
    if (linger && told == NULL) {
      by = wake_deadline(self, timeout);
    }
    if (handoff != NULL) {
      handoff_loop_free(handoff, 1);
    }
    if (linger) {
      long long from = monotonic_ns();
      if (by == LLONG_MAX || by > from) { /* not when a timer is due already */
        handoff_loop_linger(handoff, &self->notifier->armed, by == LLONG_MAX ? -1 : by - from);
        if (timeout > 0) {
          long long spent = monotonic_ns() - from;
          timeout = timeout > spent ? timeout - spent : 0;
        }
      }
    }
    ret = rcl_wait(ws, (int64_t)timeout);
    if (told != NULL) {
      atomic_store(&told->wake_by, LLONG_MAX);
    }
    if (handoff != NULL) {
      handoff_loop_free(handoff, 0);
    }
    Py_END_ALLOW_THREADS
    self->waiting = 0;
  }
  if (ret == RCL_RET_TIMEOUT) {
    /* Nothing ready: rcl cleared every slot. */
    return Py_BuildValue("()");
  }
  if (ret != RCL_RET_OK) {
    return rcl_failed("rcl_wait");
  }
  return Py_BuildValue(
    "(NNNNNN)",
    ready_of((const void * const *)ws->subscriptions, ws->size_of_subscriptions),
    ready_of((const void * const *)ws->guard_conditions, ws->size_of_guard_conditions),
    ready_of((const void * const *)ws->timers, ws->size_of_timers),
    ready_of((const void * const *)ws->clients, ws->size_of_clients),
    ready_of((const void * const *)ws->services, ws->size_of_services),
    ready_of((const void * const *)ws->events, ws->size_of_events));
}

/* timers_waited -> int: how many timers the last wait gave rcl_wait (tests: the others wait in the heap). */
static PyObject * WaitSet_get_timers_waited(WaitSetObject * self, void * Py_UNUSED(closure))
{
  return PyLong_FromSize_t(self->timers_waited);
}

static PyGetSetDef WaitSet_getset[] = {
  {"timers_waited", (getter)WaitSet_get_timers_waited, NULL,
   "How many timers the last wait gave rcl_wait (the others wait for their deadline apart).", NULL},
  {NULL, NULL, NULL, NULL, NULL},
};

static PyMethodDef WaitSet_methods[] = {
  {"wait", (PyCFunction)(void (*)(void))WaitSet_wait, METH_FASTCALL,
   "wait(timeout_ns, poll=False) -> () on timeout, else the ready addresses: (subscriptions, guard_conditions, "
   "timers, clients, services, events)"},
  {"close", (PyCFunction)WaitSet_close, METH_NOARGS, "close() -> None: let every handle go"},
  {NULL, NULL, 0, NULL},
};

PyTypeObject WaitSetType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.WaitSet",
  .tp_doc = "An rcl wait set over fixed entities: fill, wait and read in one call.",
  .tp_basicsize = sizeof(WaitSetObject),
  .tp_flags = Py_TPFLAGS_DEFAULT,
  .tp_new = PyType_GenericNew,
  .tp_init = (initproc)WaitSet_init,
  .tp_dealloc = (destructor)WaitSet_dealloc,
  .tp_methods = WaitSet_methods,
  .tp_getset = WaitSet_getset,
};

