/* _fastpath: the executor's hot path in C: readiness, takes, the async chain.
 *
 * Notifier: event-driven readiness for rcl subscriptions, clients and services.
 *
 * Why: a wait set is level-triggered and rebuilt (attached, detached) on
 * every rcl_wait, and a message published by one node of this process to
 * another is only found by the next wait. rmw offers a per-entity "new data"
 * callback instead, which Fast DDS calls in the publishing thread for a
 * reader of the same process, or in its receive thread for a remote writer.
 * This module registers that callback, records which entities became ready,
 * and triggers one rcl guard condition only while the executor's thread is
 * actually asleep in rcl_wait (armed). The executor then takes what is
 * ready without another wait: a ping-pong between two nodes of one process
 * never enters rcl_wait at all. Nor is it triggered when a lane's worker
 * publishes to a plain callback it will carry on to itself, while the
 * waiter wakes within DEFER_MAX_NS anyway (see on_event).
 *
 * Entities are identified by their rcl handle's address, which rclpy exposes
 * as ``handle.pointer``. The caller keeps each handle alive (held) from
 * ``watch`` until ``unwatch``: after ``unwatch`` returns no callback runs
 * for it any more (rmw serialises setting and calling the callback).
 *
 * WaitSet: an rcl wait set over entities given once (by handle address),
 * filled, waited on and read in one call: rclpy's wait set takes a call per
 * entity to fill and one per kind to read, on every wait.
 *
 * Taker: rcl_take of one subscription into a C message kept across takes,
 * converted with the message type's own rosidl capsules; what rclpy's
 * take_message does, without rebuilding the message, the pybind11 call
 * and the message-info dictionary nobody asked for.
 *
 * Express: the loop thread's chain of async def subscription callbacks
 * (take, admit to the callback group's lane, first step, release) without
 * returning to Python between messages, and the same for async def timer
 * callbacks after a wait; see its own comment below.
 */
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

static long long monotonic_ns(void)
{
  struct timespec now;
  clock_gettime(CLOCK_MONOTONIC, &now);
  return (long long)now.tv_sec * 1000000000LL + now.tv_nsec;
}

/* NULL, with RuntimeError "<call> failed: <rcl's error>" set and rcl's error reset. */
static PyObject * rcl_failed(const char * call)
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
 * skipped all of them. */
#define DEFER_MAX_NS 5000000LL

/* Set on lane worker threads that, after every plain callback, take what it
 * published for other plain callbacks themselves (Notifier.carry). */
static _Thread_local int carrier_thread = 0;
/* Whether any thread was ever marked: until then no publish can be deferred,
 * and a wait need not work out when it ends (an async-only process). */
static atomic_int carriers_exist = 0;

/* The event count that means "take until nothing is left". */
#define DRAIN ((size_t)1 << 30)

typedef struct Slot {
  struct NotifierObject * owner;
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
  rcl_guard_condition_t * guard; /* under lock */
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

static void trigger(rcl_guard_condition_t * guard)
{
  if (rcl_trigger_guard_condition(guard) != RCL_RET_OK) {
    rcl_reset_error(); /* a guard being destroyed: the waiter is going away too */
  }
}

static void on_event(const void * user_data, size_t number_of_events)
{
  Slot * slot = (Slot *)user_data;
  NotifierObject * self;
  if (slot == NULL || number_of_events == 0) {
    return;
  }
  self = slot->owner;
  pthread_mutex_lock(&self->lock);
  slot->count = slot->count + number_of_events < DRAIN ? slot->count + number_of_events : DRAIN;
  if (!slot->queued) {
    if (self->nready == self->capacity) {
      size_t capacity = self->capacity ? self->capacity * 2 : 16;
      Slot ** grown = realloc(self->ready, capacity * sizeof(Slot *));
      if (grown == NULL) {
        /* Out of memory: the entity is still ready in rmw; wake the thread,
         * whose next full poll takes it. */
        atomic_store(&self->pending, 1);
        if (self->guard != NULL) {
          trigger(self->guard);
        }
        pthread_mutex_unlock(&self->lock);
        return;
      }
      self->ready = grown;
      self->capacity = capacity;
    }
    self->ready[self->nready++] = slot;
    slot->queued = 1;
    if (slot->plain) {
      atomic_fetch_add(&self->plain_pending, 1);
    }
  }
  pthread_mutex_unlock(&self->lock);
  /* Dekker with arm(): either the waiter sees pending, or we see armed. */
  atomic_store(&self->pending, 1);
  /* A plain callback on a carrier thread published to another plain
   * callback: the carrier takes that message itself once its callback
   * returns, so waking the waiter now would only have it find nothing (and
   * fight the carrier for the GIL): measured, that wake-up was a quarter
   * to nearly half of a plain timer's cost. Skipped only while the waiter
   * wakes within DEFER_MAX_NS anyway, and finds the message then (pending
   * stays set), in case the callback runs on long after publishing. */
  if (slot->plain && carrier_thread) {
    long long by = atomic_load(&self->wake_by);
    if (by != LLONG_MAX && by - monotonic_ns() <= DEFER_MAX_NS) {
      return;
    }
  }
  if (atomic_exchange(&self->armed, 0)) {
    pthread_mutex_lock(&self->lock);
    if (self->guard != NULL) {
      atomic_fetch_add(&self->triggers, 1);
      trigger(self->guard);
    }
    pthread_mutex_unlock(&self->lock);
  }
}

static rcl_ret_t set_callback(int kind, uintptr_t key, rcl_event_callback_t callback, const void * data)
{
  switch (kind) {
    case KIND_SUBSCRIPTION:
      return rcl_subscription_set_on_new_message_callback((const rcl_subscription_t *)key, callback, data);
    case KIND_CLIENT:
      return rcl_client_set_on_new_response_callback((const rcl_client_t *)key, callback, data);
    case KIND_SERVICE:
      return rcl_service_set_on_new_request_callback((const rcl_service_t *)key, callback, data);
    default:
      return rcl_event_set_callback((const rcl_event_t *)key, callback, data);
  }
}

static int Notifier_init(NotifierObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {"guard", NULL};
  unsigned long long guard;
  if (!PyArg_ParseTupleAndKeywords(args, kwargs, "K", keywords, &guard)) {
    return -1;
  }
  if (guard == 0) {
    PyErr_SetString(PyExc_ValueError, "guard must be an rcl guard condition's address");
    return -1;
  }
  pthread_mutex_lock(&self->lock);
  self->guard = (rcl_guard_condition_t *)(uintptr_t)guard;
  pthread_mutex_unlock(&self->lock);
  return 0;
}

static PyObject * Notifier_new(PyTypeObject * type, PyObject * args, PyObject * kwargs)
{
  NotifierObject * self = (NotifierObject *)type->tp_alloc(type, 0);
  (void)args;
  (void)kwargs;
  if (self == NULL) {
    return NULL;
  }
  pthread_mutex_init(&self->lock, NULL);
  atomic_init(&self->armed, 0);
  atomic_init(&self->pending, 0);
  atomic_init(&self->plain_pending, 0);
  atomic_init(&self->triggers, 0);
  atomic_init(&self->wake_by, LLONG_MAX);
  self->guard = NULL;
  self->slots = NULL;
  self->ready = NULL;
  self->nready = self->capacity = 0;
  return (PyObject *)self;
}

static void Notifier_dealloc(NotifierObject * self)
{
  /* Slots still watched are leaked on purpose: rmw may still call into
   * them if their entity lives on. Their owner pointer must then stay
   * valid too, so a notifier with watched slots is never freed. */
  if (self->slots != NULL) {
    return;
  }
  free(self->ready);
  pthread_mutex_destroy(&self->lock);
  Py_TYPE(self)->tp_free((PyObject *)self);
}

static Slot * find(NotifierObject * self, uintptr_t key, Slot *** link)
{
  Slot ** at = &self->slots;
  while (*at != NULL && (*at)->key != key) {
    at = &(*at)->next;
  }
  if (link != NULL) {
    *link = at;
  }
  return *at;
}

static PyObject * Notifier_watch(NotifierObject * self, PyObject * args)
{
  unsigned long long key;
  int kind;
  int plain = 0;
  Slot * slot;
  rcl_ret_t ret;
  if (!PyArg_ParseTuple(args, "Ki|p", &key, &kind, &plain)) {
    return NULL;
  }
  if (key == 0 || kind < KIND_SUBSCRIPTION || kind > KIND_EVENT) {
    PyErr_SetString(PyExc_ValueError, "watch() needs a handle address and a known kind");
    return NULL;
  }
  if (find(self, (uintptr_t)key, NULL) != NULL) {
    Py_RETURN_FALSE;
  }
  slot = calloc(1, sizeof(Slot));
  if (slot == NULL) {
    return PyErr_NoMemory();
  }
  slot->owner = self;
  slot->key = (uintptr_t)key;
  slot->kind = kind;
  slot->plain = plain;
  slot->next = self->slots;
  self->slots = slot;
  /* rmw calls back at once, in this thread, if data is already waiting:
   * our lock must not be held here. */
  Py_BEGIN_ALLOW_THREADS
  ret = set_callback(kind, slot->key, on_event, slot);
  Py_END_ALLOW_THREADS
  if (ret != RCL_RET_OK) {
    self->slots = slot->next;
    free(slot);
    rcl_reset_error();
    PyErr_Format(
      ret == RCL_RET_UNSUPPORTED ? PyExc_NotImplementedError : PyExc_RuntimeError,
      "rmw refused a new-data callback (rcl error %d)", (int)ret);
    return NULL;
  }
  /* rmw reports only data it has not reported before: what it reported to
   * an earlier watch of this entity and nobody took would never be named
   * again. A fresh watch therefore asks for everything waiting once. Not
   * for a QoS event: taking one that did not fire returns a status anyway
   * (a bogus "incompatible QoS" warning), and rmw reports a pending one. */
  if (kind != KIND_EVENT) {
    on_event(slot, DRAIN);
  }
  Py_RETURN_TRUE;
}

static PyObject * Notifier_unwatch(NotifierObject * self, PyObject * arg)
{
  unsigned long long key = PyLong_AsUnsignedLongLong(arg);
  Slot ** link;
  Slot * slot;
  rcl_ret_t ret;
  size_t i;
  if (PyErr_Occurred()) {
    return NULL;
  }
  slot = find(self, (uintptr_t)key, &link);
  if (slot == NULL) {
    Py_RETURN_FALSE;
  }
  Py_BEGIN_ALLOW_THREADS
  ret = set_callback(slot->kind, slot->key, NULL, NULL);
  Py_END_ALLOW_THREADS
  if (ret != RCL_RET_OK) {
    rcl_reset_error();
  }
  *link = slot->next;
  pthread_mutex_lock(&self->lock);
  for (i = 0; i < self->nready; ++i) {
    if (self->ready[i] == slot) {
      memmove(&self->ready[i], &self->ready[i + 1], (self->nready - i - 1) * sizeof(Slot *));
      --self->nready;
      if (slot->plain) {
        atomic_fetch_sub(&self->plain_pending, 1);
      }
      break;
    }
  }
  pthread_mutex_unlock(&self->lock);
  free(slot);
  Py_RETURN_TRUE;
}

/* Called just before rcl_wait: returns True when something is already
 * ready (then the caller must not block). Otherwise stays armed until the
 * first new-data callback triggers the guard, or until disarm(). */
static PyObject * Notifier_arm(NotifierObject * self, PyObject * Py_UNUSED(ignored))
{
  atomic_store(&self->armed, 1);
  if (atomic_load(&self->pending)) {
    atomic_store(&self->armed, 0);
    Py_RETURN_TRUE;
  }
  Py_RETURN_FALSE;
}

static PyObject * Notifier_disarm(NotifierObject * self, PyObject * Py_UNUSED(ignored))
{
  atomic_store(&self->armed, 0);
  Py_RETURN_NONE;
}

static PyObject * Notifier_pending(NotifierObject * self, PyObject * Py_UNUSED(ignored))
{
  return PyBool_FromLong(atomic_load(&self->pending));
}

/* Everything reported has been handed out: clear the queue (under lock). */
static void forget_reported(NotifierObject * self)
{
  size_t i;
  for (i = 0; i < self->nready; ++i) {
    self->ready[i]->queued = 0;
    self->ready[i]->count = 0;
  }
  self->nready = 0;
  atomic_store(&self->plain_pending, 0);
}

/* The keys of the entities that became ready since the last call, oldest
 * first; each appears once however many events it had. */
static PyObject * Notifier_ready(NotifierObject * self, PyObject * Py_UNUSED(ignored))
{
  PyObject * list;
  size_t i;
  if (!atomic_load(&self->pending)) {
    return PyList_New(0);
  }
  pthread_mutex_lock(&self->lock);
  atomic_store(&self->pending, 0);
  list = PyList_New((Py_ssize_t)self->nready);
  if (list != NULL) {
    for (i = 0; i < self->nready; ++i) {
      PyObject * item = Py_BuildValue(
        "(Kn)", (unsigned long long)self->ready[i]->key, (Py_ssize_t)self->ready[i]->count);
      if (item == NULL) {
        Py_CLEAR(list);
        break;
      }
      PyList_SET_ITEM(list, (Py_ssize_t)i, item);
    }
    if (list != NULL) {
      forget_reported(self);
    }
  }
  if (list == NULL) {
    atomic_store(&self->pending, 1);
  }
  pthread_mutex_unlock(&self->lock);
  return list;
}

/* Like ready(), for plain slots only; the others stay queued for ready().
 * A worker thread that just ran a plain callback takes what that callback's
 * publishes made ready for other plain callbacks, and runs the next one
 * itself instead of waking another thread. */
static PyObject * Notifier_carry(NotifierObject * self, PyObject * Py_UNUSED(ignored))
{
  PyObject * list;
  size_t i;
  size_t kept = 0;
  if (!atomic_load(&self->plain_pending)) {
    return PyList_New(0);
  }
  list = PyList_New(0);
  if (list == NULL) {
    return NULL;
  }
  pthread_mutex_lock(&self->lock);
  for (i = 0; i < self->nready; ++i) {
    Slot * slot = self->ready[i];
    if (!slot->plain) {
      self->ready[kept++] = slot;
      continue;
    }
    PyObject * item = Py_BuildValue("(Kn)", (unsigned long long)slot->key, (Py_ssize_t)slot->count);
    if (item == NULL || PyList_Append(list, item) < 0) {
      Py_XDECREF(item);
      /* Leave this and the rest queued for ready(). */
      for (; i < self->nready; ++i) {
        self->ready[kept++] = self->ready[i];
      }
      Py_CLEAR(list);
      break;
    }
    Py_DECREF(item);
    slot->queued = 0;
    slot->count = 0;
    atomic_fetch_sub(&self->plain_pending, 1);
  }
  self->nready = kept;
  if (kept == 0) {
    atomic_store(&self->pending, 0);
  }
  pthread_mutex_unlock(&self->lock);
  return list;
}

/* Stop triggering the guard (it is about to be destroyed). */
static PyObject * Notifier_close(NotifierObject * self, PyObject * Py_UNUSED(ignored))
{
  pthread_mutex_lock(&self->lock);
  self->guard = NULL;
  pthread_mutex_unlock(&self->lock);
  Py_RETURN_NONE;
}

static PyObject * Notifier_get_triggers(NotifierObject * self, void * Py_UNUSED(closure))
{
  return PyLong_FromUnsignedLong(atomic_load(&self->triggers));
}

static PyObject * Notifier_get_watched(NotifierObject * self, void * Py_UNUSED(closure))
{
  Py_ssize_t count = 0;
  Slot * slot;
  for (slot = self->slots; slot != NULL; slot = slot->next) {
    ++count;
  }
  return PyLong_FromSsize_t(count);
}

static PyMethodDef Notifier_methods[] = {
  {"watch", (PyCFunction)Notifier_watch, METH_VARARGS,
   "watch(pointer, kind, plain=False) -> bool: report new data of this rcl entity (False: already watched)."},
  {"unwatch", (PyCFunction)Notifier_unwatch, METH_O,
   "unwatch(pointer) -> bool: stop; no callback for it runs once this returns."},
  {"arm", (PyCFunction)Notifier_arm, METH_NOARGS,
   "arm() -> bool: about to wait; True if something is ready already (do not block)."},
  {"disarm", (PyCFunction)Notifier_disarm, METH_NOARGS, "disarm(): back from the wait."},
  {"pending", (PyCFunction)Notifier_pending, METH_NOARGS, "pending() -> bool: something is ready."},
  {"carry", (PyCFunction)Notifier_carry, METH_NOARGS,
   "carry() -> [(address, count)]: what ready() would give, of the plain slots only."},
  {"ready", (PyCFunction)Notifier_ready, METH_NOARGS,
   "ready() -> list[tuple[int, int]]: (entity, events) that became ready since the last call."},
  {"close", (PyCFunction)Notifier_close, METH_NOARGS, "close(): never trigger the guard again."},
  {NULL, NULL, 0, NULL},
};

static PyGetSetDef Notifier_getset[] = {
  {"triggers", (getter)Notifier_get_triggers, NULL, "How often a callback woke the waiter.", NULL},
  {"watched", (getter)Notifier_get_watched, NULL, "How many entities are watched.", NULL},
  {NULL, NULL, NULL, NULL, NULL},
};

static PyTypeObject NotifierType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.Notifier",
  .tp_doc = "New-data callbacks of rcl entities, turned into a ready list and one guard trigger.",
  .tp_basicsize = sizeof(NotifierObject),
  .tp_flags = Py_TPFLAGS_DEFAULT,
  .tp_new = Notifier_new,
  .tp_init = (initproc)Notifier_init,
  .tp_dealloc = (destructor)Notifier_dealloc,
  .tp_methods = Notifier_methods,
  .tp_getset = Notifier_getset,
};

/* ------------------------------------------------------------------------ */
enum { WS_SUBSCRIPTIONS, WS_GUARDS, WS_TIMERS, WS_CLIENTS, WS_SERVICES, WS_EVENTS, WS_KINDS };

typedef struct {
  PyObject_HEAD
  rcl_wait_set_t wait_set;
  int initialised;
  void ** entities[WS_KINDS];
  size_t counts[WS_KINDS];
  NotifierObject * notifier; /* told when each wait ends at the latest, or NULL */
} WaitSetObject;

static int addresses(PyObject * sequence, void *** out, size_t * count)
{
  PyObject * fast = PySequence_Fast(sequence, "entities must be a sequence of handle addresses");
  Py_ssize_t i, n;
  if (fast == NULL) {
    return -1;
  }
  n = PySequence_Fast_GET_SIZE(fast);
  *out = calloc(n > 0 ? (size_t)n : 1, sizeof(void *));
  if (*out == NULL) {
    Py_DECREF(fast);
    PyErr_NoMemory();
    return -1;
  }
  for (i = 0; i < n; ++i) {
    unsigned long long address = PyLong_AsUnsignedLongLong(PySequence_Fast_GET_ITEM(fast, i));
    if (PyErr_Occurred()) {
      Py_DECREF(fast);
      return -1;
    }
    if (address == 0) {
      Py_DECREF(fast);
      PyErr_SetString(PyExc_ValueError, "a handle address is 0");
      return -1;
    }
    (*out)[i] = (void *)(uintptr_t)address;
  }
  *count = (size_t)n;
  Py_DECREF(fast);
  return 0;
}

static int WaitSet_init(WaitSetObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {
    "context", "subscriptions", "guard_conditions", "timers", "clients", "services", "events", "notifier",
    NULL};
  unsigned long long context;
  PyObject * notifier = Py_None;
  PyObject * given[WS_KINDS] = {NULL, NULL, NULL, NULL, NULL, NULL};
  PyObject * empty;
  rcl_ret_t ret;
  int kind;
  if (self->initialised) {
    PyErr_SetString(PyExc_RuntimeError, "WaitSet is initialised once");
    return -1;
  }
  if (!PyArg_ParseTupleAndKeywords(
      args, kwargs, "K|$OOOOOOO", keywords, &context, &given[WS_SUBSCRIPTIONS], &given[WS_GUARDS],
      &given[WS_TIMERS], &given[WS_CLIENTS], &given[WS_SERVICES], &given[WS_EVENTS], &notifier))
  {
    return -1;
  }
  if (notifier != Py_None && !PyObject_TypeCheck(notifier, &NotifierType)) {
    PyErr_SetString(PyExc_TypeError, "notifier must be a Notifier or None");
    return -1;
  }
  if (context == 0) {
    PyErr_SetString(PyExc_ValueError, "context must be an rcl context's address");
    return -1;
  }
  empty = PyTuple_New(0);
  if (empty == NULL) {
    return -1;
  }
  for (kind = 0; kind < WS_KINDS; ++kind) {
    if (addresses(given[kind] != NULL ? given[kind] : empty, &self->entities[kind], &self->counts[kind]) < 0) {
      Py_DECREF(empty);
      return -1;
    }
  }
  Py_DECREF(empty);
  self->wait_set = rcl_get_zero_initialized_wait_set();
  ret = rcl_wait_set_init(
    &self->wait_set, self->counts[WS_SUBSCRIPTIONS], self->counts[WS_GUARDS], self->counts[WS_TIMERS],
    self->counts[WS_CLIENTS], self->counts[WS_SERVICES], self->counts[WS_EVENTS],
    (rcl_context_t *)(uintptr_t)context, rcl_get_default_allocator());
  if (ret != RCL_RET_OK) {
    rcl_failed("rcl_wait_set_init");
    return -1;
  }
  if (notifier != Py_None) {
    Py_INCREF(notifier);
    self->notifier = (NotifierObject *)notifier;
  }
  self->initialised = 1;
  return 0;
}

static void WaitSet_dealloc(WaitSetObject * self)
{
  int kind;
  if (self->initialised && rcl_wait_set_fini(&self->wait_set) != RCL_RET_OK) {
    rcl_reset_error();
  }
  for (kind = 0; kind < WS_KINDS; ++kind) {
    free(self->entities[kind]);
  }
  Py_XDECREF(self->notifier);
  Py_TYPE(self)->tp_free((PyObject *)self);
}

static rcl_ret_t fill(WaitSetObject * self)
{
  rcl_wait_set_t * ws = &self->wait_set;
  rcl_ret_t ret = rcl_wait_set_clear(ws);
  size_t i;
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_SUBSCRIPTIONS]; ++i) {
    ret = rcl_wait_set_add_subscription(ws, self->entities[WS_SUBSCRIPTIONS][i], NULL);
  }
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_GUARDS]; ++i) {
    ret = rcl_wait_set_add_guard_condition(ws, self->entities[WS_GUARDS][i], NULL);
  }
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_TIMERS]; ++i) {
    ret = rcl_wait_set_add_timer(ws, self->entities[WS_TIMERS][i], NULL);
  }
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_CLIENTS]; ++i) {
    ret = rcl_wait_set_add_client(ws, self->entities[WS_CLIENTS][i], NULL);
  }
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_SERVICES]; ++i) {
    ret = rcl_wait_set_add_service(ws, self->entities[WS_SERVICES][i], NULL);
  }
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_EVENTS]; ++i) {
    ret = rcl_wait_set_add_event(ws, self->entities[WS_EVENTS][i], NULL);
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
 * override, which only their clock's jumps wake); LLONG_MAX when unknown. */
static long long wake_deadline(WaitSetObject * self, long long timeout)
{
  long long soonest = timeout >= 0 ? timeout : LLONG_MAX;
  size_t i;
  for (i = 0; i < self->counts[WS_TIMERS]; ++i) {
    const rcl_timer_t * timer = self->entities[WS_TIMERS][i];
    rcl_clock_t * clock = NULL;
    int64_t until = 0;
    rcl_ret_t ret = rcl_timer_clock((rcl_timer_t *)timer, &clock);
    if (ret == RCL_RET_OK && clock->type == RCL_ROS_TIME) {
      bool overridden = false;
      ret = rcl_is_enabled_ros_time_override(clock, &overridden);
      if (ret == RCL_RET_OK && overridden) {
        continue;
      }
    }
    if (ret == RCL_RET_OK) {
      ret = rcl_timer_get_time_until_next_call(timer, &until);
    }
    if (ret == RCL_RET_TIMER_CANCELED) {
      rcl_reset_error();
      continue;
    }
    if (ret != RCL_RET_OK) {
      rcl_reset_error();
      return LLONG_MAX;
    }
    if (until < soonest) {
      soonest = until > 0 ? until : 0;
    }
  }
  return soonest == LLONG_MAX ? LLONG_MAX : monotonic_ns() + soonest;
}

/* The longest a poll may hold the GIL in rcl_wait, should its guard
 * condition not be in the wait set after all (destroyed at shutdown). */
#define POLL_HOLD_MAX_NS 1000000LL

static long long poll_timeout(long long timeout)
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
    PyErr_SetString(PyExc_RuntimeError, "WaitSet not initialised");
    return NULL;
  }
  ret = fill(self);
  if (ret == RCL_RET_OK && poll) {
    ret = rcl_wait(ws, (int64_t)poll_timeout(timeout));
  } else if (ret == RCL_RET_OK) {
    /* Only a carrier's publish reads it (on_event). */
    NotifierObject * told = atomic_load(&carriers_exist) ? self->notifier : NULL;
    Py_BEGIN_ALLOW_THREADS
    if (told != NULL) {
      atomic_store(&told->wake_by, wake_deadline(self, timeout));
    }
    ret = rcl_wait(ws, (int64_t)timeout);
    if (told != NULL) {
      atomic_store(&told->wake_by, LLONG_MAX);
    }
    Py_END_ALLOW_THREADS
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

static PyMethodDef WaitSet_methods[] = {
  {"wait", (PyCFunction)(void (*)(void))WaitSet_wait, METH_FASTCALL,
   "wait(timeout_ns, poll=False) -> () on timeout, else the ready addresses: (subscriptions, guard_conditions, "
   "timers, clients, services, events)"},
  {NULL, NULL, 0, NULL},
};

static PyTypeObject WaitSetType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.WaitSet",
  .tp_doc = "An rcl wait set over fixed entities: fill, wait and read in one call.",
  .tp_basicsize = sizeof(WaitSetObject),
  .tp_flags = Py_TPFLAGS_DEFAULT,
  .tp_new = PyType_GenericNew,
  .tp_init = (initproc)WaitSet_init,
  .tp_dealloc = (destructor)WaitSet_dealloc,
  .tp_methods = WaitSet_methods,
};

/* ------------------------------------------------------------------------ */
typedef void * (*create_message_t)(void);
typedef void (*destroy_message_t)(void *);
typedef PyObject * (*convert_to_py_t)(void *);

typedef struct {
  PyObject_HEAD
  const rcl_subscription_t * subscription;
  void * message;
  destroy_message_t destroy;
  convert_to_py_t to_py;
  int with_gid; /* the message info carries publisher_gid, as rclpy 9's does */
} TakerObject;

/* A gid as rclpy 9 gives it in message info: {"implementation_identifier", "data"}. */
static PyObject * gid_dict(const rmw_gid_t * gid)
{
  return Py_BuildValue(
    "{s:s,s:y#}", "implementation_identifier", gid->implementation_identifier, "data",
    (const char *)gid->data, (Py_ssize_t)RMW_GID_STORAGE_SIZE);
}

static void * capsule_of(PyObject * type, const char * name)
{
  void * pointer;
  PyObject * capsule = PyObject_GetAttrString(type, name);
  if (capsule == NULL) {
    return NULL;
  }
  pointer = PyCapsule_GetPointer(capsule, NULL);
  Py_DECREF(capsule);
  return pointer;
}

static int Taker_init(TakerObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {"subscription", "message_type", "publisher_gid", NULL};
  unsigned long long subscription;
  PyObject * type;
  create_message_t create;
  int with_gid = 0;
  if (!PyArg_ParseTupleAndKeywords(args, kwargs, "KO|$p", keywords, &subscription, &type, &with_gid)) {
    return -1;
  }
  self->with_gid = with_gid;
  if (subscription == 0 || self->message != NULL) {
    PyErr_SetString(PyExc_ValueError, "Taker needs an rcl subscription's address, once");
    return -1;
  }
  create = (create_message_t)capsule_of(type, "_CREATE_ROS_MESSAGE");
  if (create == NULL) {
    return -1;
  }
  self->destroy = (destroy_message_t)capsule_of(type, "_DESTROY_ROS_MESSAGE");
  if (self->destroy == NULL) {
    return -1;
  }
  self->to_py = (convert_to_py_t)capsule_of(type, "_CONVERT_TO_PY");
  if (self->to_py == NULL) {
    return -1;
  }
  self->message = create();
  if (self->message == NULL) {
    PyErr_NoMemory();
    return -1;
  }
  self->subscription = (const rcl_subscription_t *)(uintptr_t)subscription;
  return 0;
}

static void Taker_dealloc(TakerObject * self)
{
  if (self->message != NULL) {
    self->destroy(self->message);
  }
  Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyObject * sequence_or_none(uint64_t value)
{
  if (value == RMW_MESSAGE_INFO_SEQUENCE_NUMBER_UNSUPPORTED) {
    Py_RETURN_NONE;
  }
  return PyLong_FromUnsignedLongLong(value);
}

/* One message: None when there is none, else the message, or with info
 * (message, info) with rclpy's keys. */
static PyObject * take(TakerObject * self, int with_info)
{
  rmw_message_info_t info = rmw_get_zero_initialized_message_info();
  rcl_ret_t ret;
  PyObject * message;
  PyObject * dict;
  if (self->message == NULL) {
    PyErr_SetString(PyExc_RuntimeError, "Taker not initialised");
    return NULL;
  }
  ret = rcl_take(self->subscription, self->message, &info, NULL);
  if (ret == RCL_RET_SUBSCRIPTION_TAKE_FAILED) {
    Py_RETURN_NONE;
  }
  if (ret != RCL_RET_OK) {
    return rcl_failed("rcl_take");
  }
  message = self->to_py(self->message);
  if (message == NULL || !with_info) {
    return message;
  }
  dict = Py_BuildValue(
    "{s:L,s:L,s:N,s:N}",
    "source_timestamp", (long long)info.source_timestamp,
    "received_timestamp", (long long)info.received_timestamp,
    "publication_sequence_number", sequence_or_none(info.publication_sequence_number),
    "reception_sequence_number", sequence_or_none(info.reception_sequence_number));
  if (dict != NULL && self->with_gid) {
    PyObject * gid = gid_dict(&info.publisher_gid);
    if (gid == NULL || PyDict_SetItemString(dict, "publisher_gid", gid) < 0) {
      Py_CLEAR(dict);
    }
    Py_XDECREF(gid);
  }
  if (dict == NULL) {
    Py_DECREF(message);
    return NULL;
  }
  return Py_BuildValue("(NN)", message, dict);
}

static PyObject * Taker_take(TakerObject * self, PyObject * Py_UNUSED(ignored))
{
  return take(self, 0);
}

static PyObject * Taker_take_with_info(TakerObject * self, PyObject * Py_UNUSED(ignored))
{
  return take(self, 1);
}

static PyMethodDef Taker_methods[] = {
  {"take", (PyCFunction)Taker_take, METH_NOARGS, "take() -> message | None"},
  {"take_with_info", (PyCFunction)Taker_take_with_info, METH_NOARGS,
   "take_with_info() -> (message, info) | None, info as rclpy's take_message gives it"},
  {NULL, NULL, 0, NULL},
};

static PyTypeObject TakerType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.Taker",
  .tp_doc = "rcl_take of one subscription, converted with its message type's capsules.",
  .tp_basicsize = sizeof(TakerObject),
  .tp_flags = Py_TPFLAGS_DEFAULT,
  .tp_new = PyType_GenericNew,
  .tp_init = (initproc)Taker_init,
  .tp_dealloc = (destructor)Taker_dealloc,
  .tp_methods = Taker_methods,
};

/* ------------------------------------------------------------------------ */
/* Lock: a mutex the Python side uses as threading.Lock (``with``, acquire,
 * release, locked) and this module checks and takes without a Python call.
 *
 * Why: the wait set's take lock is taken once per batch of the async chain
 * and a lane's lock is looked at twice per callback; through threading.Lock
 * that is a bound-method call each, whose argument parsing alone cost about
 * 2% of a ping-pong (measured with perf on 3.12). ``locked`` is kept in the
 * object: every acquire and release happens with the GIL held (a blocked
 * acquire lets the GIL go only while it waits), so the field is exact for
 * any thread holding the GIL. */
typedef struct {
  PyObject_HEAD
  PyThread_type_lock lock;
  int locked;
} LockObject;

static PyTypeObject LockType;

#define IS_LOCK(object) (Py_TYPE(object) == &LockType)

/* Take the lock without waiting: 1 taken, 0 busy. */
static int lock_try(LockObject * self)
{
  if (self->locked || !PyThread_acquire_lock(self->lock, NOWAIT_LOCK)) {
    return 0;
  }
  self->locked = 1;
  return 1;
}

static void lock_release(LockObject * self)
{
  self->locked = 0;
  PyThread_release_lock(self->lock);
}

static PyObject * Lock_new(PyTypeObject * type, PyObject * args, PyObject * kwargs)
{
  LockObject * self;
  if ((args != NULL && PyTuple_GET_SIZE(args) != 0) || (kwargs != NULL && PyDict_GET_SIZE(kwargs) != 0)) {
    PyErr_SetString(PyExc_TypeError, "Lock() takes no arguments");
    return NULL;
  }
  self = (LockObject *)type->tp_alloc(type, 0);
  if (self == NULL) {
    return NULL;
  }
  self->lock = PyThread_allocate_lock();
  if (self->lock == NULL) {
    Py_DECREF(self);
    return PyErr_NoMemory();
  }
  return (PyObject *)self;
}

static void Lock_dealloc(LockObject * self)
{
  if (self->lock != NULL) {
    if (self->locked) {
      PyThread_release_lock(self->lock);
    }
    PyThread_free_lock(self->lock);
  }
  Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyObject * Lock_acquire(LockObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {"blocking", "timeout", NULL};
  int blocking = 1;
  double timeout = -1.0;
  PY_TIMEOUT_T microseconds;
  PyLockStatus status;
  if ((args != NULL || kwargs != NULL) &&
      !PyArg_ParseTupleAndKeywords(args, kwargs, "|pd:acquire", keywords, &blocking, &timeout)) {
    return NULL;
  }
  if (!blocking && timeout != -1.0) {
    PyErr_SetString(PyExc_ValueError, "can't specify a timeout for a non-blocking call");
    return NULL;
  }
  if (timeout < 0 && timeout != -1.0) {
    PyErr_SetString(PyExc_ValueError, "timeout value must be a non-negative number");
    return NULL;
  }
  if (lock_try(self)) {
    Py_RETURN_TRUE;
  }
  if (!blocking) {
    Py_RETURN_FALSE;
  }
  microseconds = timeout < 0 ? -1 : (PY_TIMEOUT_T)(timeout * 1e6);
  Py_BEGIN_ALLOW_THREADS
  status = PyThread_acquire_lock_timed(self->lock, microseconds, 0);
  Py_END_ALLOW_THREADS
  if (status != PY_LOCK_ACQUIRED) {
    Py_RETURN_FALSE;
  }
  self->locked = 1;
  Py_RETURN_TRUE;
}

static PyObject * Lock_enter(LockObject * self, PyObject * Py_UNUSED(ignored))
{
  return Lock_acquire(self, NULL, NULL);
}

static PyObject * Lock_release(LockObject * self, PyObject * Py_UNUSED(ignored))
{
  if (!self->locked) {
    PyErr_SetString(PyExc_RuntimeError, "release unlocked lock");
    return NULL;
  }
  lock_release(self);
  Py_RETURN_NONE;
}

static PyObject * Lock_exit(LockObject * self, PyObject * Py_UNUSED(args))
{
  return Lock_release(self, NULL);
}

static PyObject * Lock_locked(LockObject * self, PyObject * Py_UNUSED(ignored))
{
  return PyBool_FromLong(self->locked);
}

static PyMethodDef Lock_methods[] = {
  {"acquire", (PyCFunction)(void (*)(void))Lock_acquire, METH_VARARGS | METH_KEYWORDS,
   "acquire(blocking=True, timeout=-1) -> bool, as threading.Lock's"},
  {"release", (PyCFunction)Lock_release, METH_NOARGS, "release() -> None"},
  {"locked", (PyCFunction)Lock_locked, METH_NOARGS, "locked() -> bool"},
  {"__enter__", (PyCFunction)Lock_enter, METH_NOARGS, NULL},
  {"__exit__", (PyCFunction)Lock_exit, METH_VARARGS, NULL},
  {NULL, NULL, 0, NULL},
};

static PyTypeObject LockType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.Lock",
  .tp_doc = "A mutex used as threading.Lock, which the compiled path checks and takes directly.",
  .tp_basicsize = sizeof(LockObject),
  .tp_flags = Py_TPFLAGS_DEFAULT,
  .tp_new = Lock_new,
  .tp_dealloc = (destructor)Lock_dealloc,
  .tp_methods = Lock_methods,
};

/* ------------------------------------------------------------------------ */
/* Express: the loop thread's chain of async subscription callbacks, in C.
 *
 * Why: a message one node of this process publishes to another is reported
 * by the Notifier at once, and the loop thread takes it and runs its
 * ``async def`` callback's first step without waiting (most callbacks
 * finish in it). Done in Python that costs about 20 calls per message
 * (taking, handing to the lane, admitting, entering the runner's task and
 * context, finishing), more than the publish and the take together. Here it
 * is one call per chain: take what the Notifier reported, admit each message
 * into its callback group's lane, run the first step in an idle runner task
 * of that lane (asyncio's current task and the runner's context, as the
 * Python path does) and release the lane.
 *
 * Only the common case is handled here; everything else is handed to the
 * Python path the executor uses anyway: a lane that is busy, locked by
 * another thread or without an idle runner (``slow``), a callback that
 * suspends or fails (``suspended``, ``failed``), a lane with pending work
 * after the step (``Lane.express_release``), and entities that are not
 * express routes (``_WaitSet._take_ready``). The lane's state is read and
 * written only while its lock is free: this thread holds the GIL and calls
 * no Python code in between, so no other thread is inside the lane then.
 *
 * Routes (a dict of handle address -> (taker, entry, lane, the lane's
 * Lock, marker, subscription, token, the attribute holding its
 * callback); see ``_route`` in _dispatch.py) are read from the wait set's current table under its take lock,
 * with its dirty and closed flags, like the Python path.
 *
 * Timers: a 100 Hz timer publishing to another node wakes the loop for a
 * callback or two, and the Python between the wait and the callback (taking
 * the timer, handing it to its lane, admitting, the first step, finishing;
 * about 30 calls) was most of what each wake-up cost after the wait itself.
 * ``call_timers`` calls the ready timers that have a route (the same, with
 * the timer's address first) where the wait set's dispatch
 * takes them, under its locks; ``run_fired`` runs their callbacks as
 * ``drain`` runs a message's, once those locks are released.
 */
typedef struct {
  PyObject_HEAD
  NotifierObject * notifier;
  PyObject * waitset;     /* the _WaitSet: _dirty, _closed, _table, _take_ready */
  PyObject * take_lock;   /* its _take_lock: a Lock, taken directly */
  PyObject * loop;
  PyObject * ready_queue; /* asyncio's ready deque: non-empty means asyncio has work */
  PyObject * eager;       /* the dispatcher's eager deque */
  PyObject * run_eager;
  PyObject * enter_task;
  PyObject * leave_task;
  PyObject * on_done;
  PyObject * done_waiters; /* on_done is called only while this is non-empty */
  PyObject * slow;        /* slow(entry, message) */
  PyObject * suspended;   /* suspended(entry, message, runner, coro, yielded, context) */
  PyObject * failed;      /* failed(entry, message, error or None) */
  PyObject * cancelled_error; /* asyncio.CancelledError: a callback's own cancellation is no error */
  PyObject * fired;       /* timer routes called by call_timers, whose callbacks run_fired runs */
  unsigned long long expressed; /* callbacks run here (tests, diagnostics) */
} ExpressObject;

static PyObject * s_dirty, * s_closed, * s_table, * s_express,
  * s_take_ready, * s_running, * s_limit, * s_idle_runners, * s_idle, * s_done,
  * s_task, * s_context, * s_current, * s_retired, * s_pending, * s_express_release;

static int intern_names(void)
{
#define INTERN(var, text) if ((var = PyUnicode_InternFromString(text)) == NULL) return -1
  INTERN(s_dirty, "_dirty");
  INTERN(s_closed, "_closed");
  INTERN(s_table, "_table");
  INTERN(s_express, "express");
  INTERN(s_take_ready, "_take_ready");
  INTERN(s_running, "_running");
  INTERN(s_limit, "limit");
  INTERN(s_idle_runners, "_idle_runners");
  INTERN(s_idle, "idle");
  INTERN(s_done, "done");
  INTERN(s_task, "task");
  INTERN(s_context, "context");
  INTERN(s_current, "current");
  INTERN(s_retired, "retired");
  INTERN(s_pending, "_pending");
  INTERN(s_express_release, "express_release");
#undef INTERN
  return 0;
}

static int Express_init(ExpressObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {
    "notifier", "waitset", "take_lock", "loop", "ready_queue", "eager", "run_eager", "enter_task", "leave_task",
    "on_done", "done_waiters", "slow", "suspended", "failed", "cancelled_error", NULL};
  PyObject * notifier, * take_lock;
  if (!PyArg_ParseTupleAndKeywords(
        args, kwargs, "$O!OOOOOOOOOOOOOO", keywords, &NotifierType, &notifier, &self->waitset,
        &take_lock, &self->loop, &self->ready_queue, &self->eager, &self->run_eager, &self->enter_task,
        &self->leave_task, &self->on_done, &self->done_waiters, &self->slow, &self->suspended, &self->failed, &self->cancelled_error)) {
    return -1;
  }
  self->notifier = (NotifierObject *)notifier;
  Py_INCREF(notifier);
  Py_INCREF(self->waitset);
  Py_INCREF(self->loop);
  Py_INCREF(self->ready_queue);
  Py_INCREF(self->eager);
  Py_INCREF(self->run_eager);
  Py_INCREF(self->enter_task);
  Py_INCREF(self->leave_task);
  Py_INCREF(self->on_done);
  Py_INCREF(self->done_waiters);
  Py_INCREF(self->slow);
  Py_INCREF(self->suspended);
  Py_INCREF(self->failed);
  Py_INCREF(self->cancelled_error);
  if (!IS_LOCK(take_lock)) {
    PyErr_SetString(PyExc_TypeError, "Express needs the wait set's take lock to be a _fastpath.Lock");
    return -1;
  }
  Py_XSETREF(self->take_lock, Py_NewRef(take_lock));
  Py_XSETREF(self->fired, PyList_New(0));
  return self->fired == NULL ? -1 : 0;
}

static int Express_traverse(ExpressObject * self, visitproc visit, void * arg)
{
  Py_VISIT(self->notifier);
  Py_VISIT(self->waitset);
  Py_VISIT(self->loop);
  Py_VISIT(self->ready_queue);
  Py_VISIT(self->eager);
  Py_VISIT(self->run_eager);
  Py_VISIT(self->enter_task);
  Py_VISIT(self->leave_task);
  Py_VISIT(self->on_done);
  Py_VISIT(self->done_waiters);
  Py_VISIT(self->slow);
  Py_VISIT(self->suspended);
  Py_VISIT(self->failed);
  Py_VISIT(self->cancelled_error);
  Py_VISIT(self->fired);
  Py_VISIT(self->take_lock);
  return 0;
}

static int Express_clear(ExpressObject * self)
{
  Py_CLEAR(self->notifier);
  Py_CLEAR(self->waitset);
  Py_CLEAR(self->loop);
  Py_CLEAR(self->ready_queue);
  Py_CLEAR(self->eager);
  Py_CLEAR(self->run_eager);
  Py_CLEAR(self->enter_task);
  Py_CLEAR(self->leave_task);
  Py_CLEAR(self->on_done);
  Py_CLEAR(self->done_waiters);
  Py_CLEAR(self->slow);
  Py_CLEAR(self->suspended);
  Py_CLEAR(self->failed);
  Py_CLEAR(self->cancelled_error);
  Py_CLEAR(self->fired);
  Py_CLEAR(self->take_lock);
  return 0;
}

static void Express_dealloc(ExpressObject * self)
{
  PyObject_GC_UnTrack(self);
  Express_clear(self);
  Py_TYPE(self)->tp_free((PyObject *)self);
}

/* 1 if the attribute is true, 0 if false, -1 on error. */
static int attr_true(PyObject * object, PyObject * name)
{
  int result;
  PyObject * value = PyObject_GetAttr(object, name);
  if (value == NULL) {
    return -1;
  }
  result = PyObject_IsTrue(value);
  Py_DECREF(value);
  return result;
}

/* Whether the lane's lock (a Lock) is free: 1 free, 0 held, -1 not a Lock. */
static int lock_free(PyObject * lock)
{
  if (!IS_LOCK(lock)) {
    PyErr_SetString(PyExc_TypeError, "a lane's lock must be a _fastpath.Lock");
    return -1;
  }
  return !((LockObject *)lock)->locked;
}

static int add_running(PyObject * lane, long delta)
{
  long running;
  int result;
  PyObject * value = PyObject_GetAttr(lane, s_running);
  if (value == NULL) {
    return -1;
  }
  running = PyLong_AsLong(value);
  Py_DECREF(value);
  if (running == -1 && PyErr_Occurred()) {
    return -1;
  }
  value = PyLong_FromLong(running + delta);
  if (value == NULL) {
    return -1;
  }
  result = PyObject_SetAttr(lane, s_running, value);
  Py_DECREF(value);
  return result;
}

/* An idle runner of ``lane`` whose first step may run now (new reference),
 * Py_None if none is (the slow path finds or makes one), NULL on error.
 * Admits too: the lane's running count is raised when one is returned. */
static PyObject * admit(PyObject * lane, PyObject * lane_lock)
{
  PyObject * runners, * runner, * idle, * done, * value;
  long running, limit;
  int free = lock_free(lane_lock);
  if (free <= 0) {
    return free < 0 ? NULL : Py_NewRef(Py_None);
  }
  switch (attr_true(lane, s_closed)) {
    case -1: return NULL;
    case 1: return Py_NewRef(Py_None);
  }
  if ((value = PyObject_GetAttr(lane, s_running)) == NULL) {
    return NULL;
  }
  running = PyLong_AsLong(value);
  Py_DECREF(value);
  if ((value = PyObject_GetAttr(lane, s_limit)) == NULL) {
    return NULL;
  }
  limit = PyLong_AsLong(value);
  Py_DECREF(value);
  if (PyErr_Occurred()) {
    return NULL;
  }
  if (running >= limit) {
    return Py_NewRef(Py_None);
  }
  if ((runners = PyObject_GetAttr(lane, s_idle_runners)) == NULL) {
    return NULL;
  }
  if (!PyList_Check(runners) || PyList_GET_SIZE(runners) == 0) {
    Py_DECREF(runners);
    return Py_NewRef(Py_None);
  }
  runner = Py_NewRef(PyList_GET_ITEM(runners, PyList_GET_SIZE(runners) - 1));
  Py_DECREF(runners);
  if ((idle = PyObject_GetAttr(runner, s_idle)) == NULL) {
    Py_DECREF(runner);
    return NULL;
  }
  if (idle == Py_None) {
    Py_DECREF(idle);
    Py_DECREF(runner);
    return Py_NewRef(Py_None);
  }
  done = PyObject_CallMethodNoArgs(idle, s_done);
  Py_DECREF(idle);
  if (done == NULL) {
    Py_DECREF(runner);
    return NULL;
  }
  if (done != Py_False) {
    Py_DECREF(done);
    Py_DECREF(runner);
    return Py_NewRef(Py_None);
  }
  Py_DECREF(done);
  if (add_running(lane, 1) < 0) {
    Py_DECREF(runner);
    return NULL;
  }
  return runner;
}

/* The lane's slot taken by ``admit`` is given back (or passed to pending work). */
static int release(PyObject * lane, PyObject * lane_lock, PyObject * marker)
{
  PyObject * pending, * result;
  Py_ssize_t waiting;
  int free = lock_free(lane_lock);
  if (free < 0) {
    return -1;
  }
  if (free) {
    if ((pending = PyObject_GetAttr(lane, s_pending)) == NULL) {
      return -1;
    }
    waiting = PyObject_Length(pending);
    Py_DECREF(pending);
    if (waiting < 0) {
      return -1;
    }
    if (waiting == 0) {
      return add_running(lane, -1);
    }
  }
  result = PyObject_CallMethodOneArg(lane, s_express_release, marker);
  Py_XDECREF(result);
  return result == NULL ? -1 : 0;
}

static PyObject * call2(PyObject * callable, PyObject * a, PyObject * b)
{
  PyObject * args[2] = {a, b};
  return PyObject_Vectorcall(callable, args, 2, NULL);
}

/* Run one taken message's callback (``message`` NULL: a called timer's,
 * without arguments): 0, or -1 with an exception set (one that must stop the
 * executor: KeyboardInterrupt, or a failure of this path). The hand-overs to
 * Python get None for a timer's message. */
static int run_one(ExpressObject * self, PyObject * route, PyObject * message)
{
  PyObject * given = message != NULL ? message : Py_None;
  PyObject * entry = PyTuple_GET_ITEM(route, 1);
  PyObject * lane = PyTuple_GET_ITEM(route, 2);
  PyObject * lane_lock = PyTuple_GET_ITEM(route, 3);
  PyObject * marker = PyTuple_GET_ITEM(route, 4);
  PyObject * entity = PyTuple_GET_ITEM(route, 5);
  PyObject * token = PyTuple_GET_ITEM(route, 6);
  PyObject * callback_attribute = PyTuple_GET_ITEM(route, 7);
  PyObject * callback, * runner, * task, * context, * coro, * yielded = NULL;
  PyObject * result, * type, * value, * traceback;
  PySendResult status;
  Py_ssize_t waiting;
  int retired;

  retired = attr_true(token, s_retired);
  if (retired != 0) {
    return retired < 0 ? -1 : 0; /* its entity or node left: dropped, as rclpy drops it */
  }
  if ((runner = admit(lane, lane_lock)) == NULL) {
    return -1;
  }
  if (runner == Py_None) {
    Py_DECREF(runner);
    result = call2(self->slow, entry, given);
    Py_XDECREF(result);
    return result == NULL ? -1 : 0;
  }
  task = PyObject_GetAttr(runner, s_task);
  /* Each callback runs in a copy of its runner's context, as each asyncio
   * task gets a copy of the context it was created in: what one callback
   * sets in a ContextVar is not the next one's. */
  {
    PyObject * shared = PyObject_GetAttr(runner, s_context);
    context = shared != NULL ? PyContext_Copy(shared) : NULL;
    Py_XDECREF(shared);
  }
  callback = PyObject_GetAttr(entity, callback_attribute);
  if (task == NULL || context == NULL || callback == NULL ||
      PyObject_SetAttr(runner, s_current, marker) < 0) {
    goto undo;
  }
  if (PyContext_Enter(context) < 0) {
    goto undo;
  }
  result = call2(self->enter_task, self->loop, task);
  if (result == NULL) {
    PyContext_Exit(context);
    goto undo;
  }
  Py_DECREF(result);
  coro = message != NULL ? PyObject_CallOneArg(callback, message) : PyObject_CallNoArgs(callback);
  status = coro != NULL ? PyIter_Send(coro, Py_None, &yielded) : PYGEN_ERROR;
  PyErr_Fetch(&type, &value, &traceback);
  result = call2(self->leave_task, self->loop, task);
  Py_XDECREF(result);
  PyContext_Exit(context);
  Py_DECREF(task);
  Py_DECREF(callback);
  if (result == NULL) { /* leaving the task failed: nothing sane is left to do */
    Py_XDECREF(type);
    Py_XDECREF(value);
    Py_XDECREF(traceback);
    Py_XDECREF(coro);
    Py_XDECREF(yielded);
    Py_DECREF(context);
    Py_DECREF(runner);
    return -1;
  }
  if (PyObject_SetAttr(runner, s_current, Py_None) < 0) {
    PyErr_Clear();
  }
  self->expressed++;
  if (status == PYGEN_RETURN) {
    Py_DECREF(coro);
    Py_XDECREF(yielded);
    Py_DECREF(context);
    Py_DECREF(runner);
    waiting = PyObject_Length(self->done_waiters);
    if (waiting != 0) {
      result = waiting > 0 ? PyObject_CallNoArgs(self->on_done) : NULL;
      Py_XDECREF(result);
      if (result == NULL) {
        return -1;
      }
    }
    return release(lane, lane_lock, marker);
  }
  if (status == PYGEN_NEXT) {
    PyObject * args[6] = {entry, given, runner, coro, yielded, context};
    result = PyObject_Vectorcall(self->suspended, args, 6, NULL);
    Py_DECREF(coro);
    Py_DECREF(yielded);
    Py_DECREF(context);
    Py_DECREF(runner);
    Py_XDECREF(result);
    return result == NULL ? -1 : 0;
  }
  /* Failed: in creating the coroutine or in its first step. */
  Py_XDECREF(coro);
  Py_DECREF(context);
  Py_DECREF(runner);
  PyErr_NormalizeException(&type, &value, &traceback);
  if (value != NULL && traceback != NULL) {
    PyException_SetTraceback(value, traceback);
  }
  if (value != NULL && PyErr_GivenExceptionMatches(value, PyExc_KeyboardInterrupt)) {
    PyErr_Restore(type, value, traceback);
    return -1;
  }
  Py_XDECREF(type);
  Py_XDECREF(traceback);
  {
    /* A callback's own cancellation ends that callback only: no error. */
    int cancelled = value != NULL && PyErr_GivenExceptionMatches(value, self->cancelled_error);
    PyObject * args[3] = {entry, given, cancelled || value == NULL ? Py_None : value};
    result = PyObject_Vectorcall(self->failed, args, 3, NULL);
  }
  Py_XDECREF(value);
  Py_XDECREF(result);
  return result == NULL ? -1 : 0;

undo:
  PyErr_Fetch(&type, &value, &traceback);
  if (PyObject_SetAttr(runner, s_current, Py_None) < 0 || add_running(lane, -1) < 0) {
    PyErr_Clear();
  }
  PyErr_Restore(type, value, traceback);
  Py_XDECREF(task);
  Py_XDECREF(context);
  Py_XDECREF(callback);
  Py_DECREF(runner);
  return -1;
}


/* How many reported entities ``take_reported`` moves without allocating. */
#define REPORTED_INLINE 16

/* What ready() gives, into C arrays (no Python objects): how many pairs were
 * moved into ``*keys`` and ``*counts`` (the given ``inline`` buffers of
 * REPORTED_INLINE, or malloc'd ones the caller frees when they differ), -1
 * out of memory (nothing consumed). */
static Py_ssize_t take_reported(
  NotifierObject * self, uintptr_t ** keys, size_t ** counts, uintptr_t * inline_keys, size_t * inline_counts)
{
  size_t i, n;
  pthread_mutex_lock(&self->lock);
  atomic_store(&self->pending, 0);
  n = self->nready;
  if (n <= REPORTED_INLINE) {
    *keys = inline_keys;
    *counts = inline_counts;
  } else {
    *keys = malloc(n * sizeof(uintptr_t));
    *counts = malloc(n * sizeof(size_t));
  }
  if (*keys == NULL || *counts == NULL) {
    free(*keys);
    free(*counts);
    *keys = inline_keys;
    *counts = inline_counts;
    atomic_store(&self->pending, 1);
    pthread_mutex_unlock(&self->lock);
    PyErr_NoMemory();
    return -1;
  }
  for (i = 0; i < n; ++i) {
    (*keys)[i] = self->ready[i]->key;
    (*counts)[i] = self->ready[i]->count;
  }
  forget_reported(self);
  pthread_mutex_unlock(&self->lock);
  return (Py_ssize_t)n;
}

/* Take what the notifier reported (into ``batch``: route, message, ...) under
 * the take lock; 1 taken, 0 nothing to do (stop), -1 error. Entities that are
 * not routes go through the wait set's Python ``_take_ready``. */
static int take_batch(ExpressObject * self, PyObject * batch)
{
  PyObject * table = NULL, * routes = NULL, * rest = NULL;
  uintptr_t inline_keys[REPORTED_INLINE];
  size_t inline_counts[REPORTED_INLINE];
  uintptr_t * keys = inline_keys;
  size_t * counts = inline_counts;
  PyObject * result, * type = NULL, * value = NULL, * traceback = NULL;
  Py_ssize_t i, n;
  int status = 1, flag;

  if (!lock_try((LockObject *)self->take_lock)) {
    /* A worker is carrying: whoever holds it takes what is plain; the
     * caller's next round (the Python path) takes the rest. */
    return 0;
  }
  if ((flag = attr_true(self->waitset, s_closed)) != 0 ||
      (flag = attr_true(self->waitset, s_dirty)) != 0) {
    status = flag < 0 ? -1 : 0;
    goto out;
  }
  if ((table = PyObject_GetAttr(self->waitset, s_table)) == NULL ||
      (routes = PyObject_GetAttr(table, s_express)) == NULL) {
    status = -1;
    goto out;
  }
  if (!PyDict_Check(routes)) {
    PyErr_SetString(PyExc_TypeError, "express routes must be a dict");
    status = -1;
    goto out;
  }
  if ((n = take_reported(self->notifier, &keys, &counts, inline_keys, inline_counts)) < 0) {
    status = -1;
    goto out;
  }
  for (i = 0; i < n; ++i) {
    PyObject * key = PyLong_FromUnsignedLongLong((unsigned long long)keys[i]);
    PyObject * route = key != NULL ? PyDict_GetItemWithError(routes, key) : NULL;
    size_t j;
    if (route == NULL) {
      PyObject * pair;
      if (PyErr_Occurred()) {
        Py_XDECREF(key);
        status = -1;
        goto out;
      }
      pair = Py_BuildValue("(Nn)", key, (Py_ssize_t)counts[i]);
      if (pair == NULL || (rest == NULL && (rest = PyList_New(0)) == NULL) || PyList_Append(rest, pair) < 0) {
        Py_XDECREF(pair);
        status = -1;
        goto out;
      }
      Py_DECREF(pair);
      continue;
    }
    Py_DECREF(key);
    for (j = 0; j < counts[i]; ++j) {
      PyObject * message = take((TakerObject *)PyTuple_GET_ITEM(route, 0), 0);
      if (message == NULL) {
        /* Run what was taken, then report this. */
        PyErr_Fetch(&type, &value, &traceback);
        goto out;
      }
      if (message == Py_None) {
        Py_DECREF(message);
        break;
      }
      if (PyList_Append(batch, route) < 0 || PyList_Append(batch, message) < 0) {
        Py_DECREF(message);
        status = -1;
        goto out;
      }
      Py_DECREF(message);
    }
  }
  if (rest != NULL) {
    PyObject * args[3] = {self->waitset, table, rest};
    result = PyObject_VectorcallMethod(s_take_ready, args, 3, NULL);
    if (result == NULL) {
      status = -1;
    }
    Py_XDECREF(result);
  }
out:
  Py_XDECREF(table);
  Py_XDECREF(routes);
  if (keys != inline_keys) {
    free(keys);
    free(counts);
  }
  Py_XDECREF(rest);
  lock_release((LockObject *)self->take_lock);
  if (type != NULL || value != NULL) {
    /* A take failed: the caller runs the batch, then raises this. */
    PyErr_Restore(type, value, traceback);
    return -2;
  }
  return status;
}

/* drain(deadline_ns) -> bool: take and run what the notifier reports until
 * nothing is, the deadline (the next poll of timers) passes, or asyncio has
 * work of its own. False: the take lock was busy (take the Python way). */
static PyObject * Express_drain(ExpressObject * self, PyObject * arg)
{
  long long deadline = PyLong_AsLongLong(arg);
  PyObject * batch;
  if (deadline == -1 && PyErr_Occurred()) {
    return NULL;
  }
  batch = PyList_New(0);
  if (batch == NULL) {
    return NULL;
  }
  for (;;) {
    Py_ssize_t i, n, queued;
    int status;
    if (!atomic_load(&self->notifier->pending) || monotonic_ns() >= deadline) {
      break;
    }
    queued = PyObject_Length(self->ready_queue);
    if (queued != 0) {
      if (queued < 0) {
        Py_DECREF(batch);
        return NULL;
      }
      break;
    }
    status = take_batch(self, batch);
    if (status == 0) {
      Py_DECREF(batch);
      Py_RETURN_FALSE;
    }
    {
      /* A failed take (-2) still runs what was taken before it. */
      PyObject * et = NULL, * ev = NULL, * tb = NULL;
      if (status == -2) {
        PyErr_Fetch(&et, &ev, &tb);
      }
      n = PyList_GET_SIZE(batch);
      for (i = 0; i + 1 < n && status != -1; i += 2) {
        if (run_one(self, PyList_GET_ITEM(batch, i), PyList_GET_ITEM(batch, i + 1)) < 0) {
          status = -1;
        }
      }
      if (status == -1) {
        Py_XDECREF(et);
        Py_XDECREF(ev);
        Py_XDECREF(tb);
      } else if (PyList_SetSlice(batch, 0, n, NULL) < 0) {
        status = -1;
      } else if (status == -2) {
        PyErr_Restore(et, ev, tb);
      }
    }
    if (status < 0) {
      Py_DECREF(batch);
      return NULL;
    }
    queued = PyObject_Length(self->eager);
    if (queued > 0) {
      PyObject * result = PyObject_CallNoArgs(self->run_eager);
      if (result == NULL) {
        Py_DECREF(batch);
        return NULL;
      }
      Py_DECREF(result);
    } else if (queued < 0) {
      Py_DECREF(batch);
      return NULL;
    }
  }
  Py_DECREF(batch);
  Py_RETURN_TRUE;
}

/* call_timers(routes, ready) -> list: call (as rcl_timer_call) each ready
 * timer that has a route, keeping the route for run_fired; the addresses
 * left to the Python path: no route, or anything unusual about the timer
 * (not ready after all, cancelled, an rcl error), which rclpy's own calls
 * there handle and report. Called under the wait set's take lock, with the
 * table whose handles keep the timers alive: no Python code runs here. */
static PyObject * Express_call_timers(ExpressObject * self, PyObject * const * args, Py_ssize_t nargs)
{
  PyObject * routes, * ready, * rest;
  Py_ssize_t i, n;
  if (nargs != 2 || !PyDict_Check(args[0])) {
    PyErr_SetString(PyExc_TypeError, "call_timers(routes: dict, ready: iterable)");
    return NULL;
  }
  routes = args[0];
  if ((ready = PySequence_Fast(args[1], "call_timers: ready must be iterable")) == NULL) {
    return NULL;
  }
  if ((rest = PyList_New(0)) == NULL) {
    Py_DECREF(ready);
    return NULL;
  }
  n = PySequence_Fast_GET_SIZE(ready);
  for (i = 0; i < n; ++i) {
    PyObject * key = PySequence_Fast_GET_ITEM(ready, i);
    PyObject * route = PyDict_GetItemWithError(routes, key);
    rcl_timer_t * timer;
    bool is_ready = false;
    if (route == NULL) {
      if (PyErr_Occurred() || PyList_Append(rest, key) < 0) {
        goto fail;
      }
      continue;
    }
    if (!PyTuple_Check(route) || PyTuple_GET_SIZE(route) != 8) {
      PyErr_SetString(PyExc_TypeError, "a timer route is a tuple of 8");
      goto fail;
    }
    timer = (rcl_timer_t *)PyLong_AsVoidPtr(PyTuple_GET_ITEM(route, 0));
    if (timer == NULL && PyErr_Occurred()) {
      goto fail;
    }
    if (rcl_timer_is_ready(timer, &is_ready) != RCL_RET_OK || !is_ready || rcl_timer_call(timer) != RCL_RET_OK) {
      rcl_reset_error();
      if (PyList_Append(rest, key) < 0) {
        goto fail;
      }
      continue;
    }
    if (PyList_Append(self->fired, route) < 0) {
      goto fail;
    }
  }
  Py_DECREF(ready);
  return rest;

fail:
  Py_DECREF(ready);
  Py_DECREF(rest);
  return NULL;
}

/* run_fired() -> None: run the callbacks of the timers call_timers called,
 * as drain runs a message's. Outside the wait set's locks (user code runs).
 * What an error stops before is kept for the next call. */
static PyObject * Express_run_fired(ExpressObject * self, PyObject * Py_UNUSED(ignored))
{
  PyObject * fired = self->fired, * fresh;
  Py_ssize_t i, n = PyList_GET_SIZE(fired);
  if (n == 0) {
    Py_RETURN_NONE;
  }
  if ((fresh = PyList_New(0)) == NULL) {
    return NULL;
  }
  self->fired = fresh; /* callbacks may fire more (through a nested spin): kept apart */
  for (i = 0; i < n; ++i) {
    if (run_one(self, PyList_GET_ITEM(fired, i), NULL) < 0) {
      /* The rest goes back in front of whatever was fired meanwhile. */
      PyObject * et, * ev, * tb;
      PyErr_Fetch(&et, &ev, &tb);
      if (PyList_SetSlice(fired, 0, i + 1, NULL) < 0 ||
          PyList_SetSlice(self->fired, 0, 0, fired) < 0) {
        PyErr_Clear();
      }
      Py_DECREF(fired);
      PyErr_Restore(et, ev, tb);
      return NULL;
    }
  }
  Py_DECREF(fired);
  Py_RETURN_NONE;
}

static PyObject * Express_get_expressed(ExpressObject * self, void * Py_UNUSED(closure))
{
  return PyLong_FromUnsignedLongLong(self->expressed);
}

static PyMethodDef Express_methods[] = {
  {"drain", (PyCFunction)Express_drain, METH_O,
   "drain(deadline_ns) -> bool: take and run reported messages until none is, the deadline, or asyncio has work; False: take lock busy."},
  {"call_timers", (PyCFunction)(void (*)(void))Express_call_timers, METH_FASTCALL,
   "call_timers(routes, ready) -> list: call the ready timers that have routes (run by run_fired); the other addresses."},
  {"run_fired", (PyCFunction)Express_run_fired, METH_NOARGS,
   "run_fired() -> None: run the callbacks of the timers call_timers called."},
  {NULL, NULL, 0, NULL},
};

static PyGetSetDef Express_getset[] = {
  {"expressed", (getter)Express_get_expressed, NULL, "How many callbacks ran on this path.", NULL},
  {NULL, NULL, NULL, NULL, NULL},
};

static PyTypeObject ExpressType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.Express",
  .tp_doc = "The loop thread's chain of async subscription callbacks: take, admit, first step, release.",
  .tp_basicsize = sizeof(ExpressObject),
  .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
  .tp_new = PyType_GenericNew,
  .tp_init = (initproc)Express_init,
  .tp_dealloc = (destructor)Express_dealloc,
  .tp_traverse = (traverseproc)Express_traverse,
  .tp_clear = (inquiry)Express_clear,
  .tp_methods = Express_methods,
  .tp_getset = Express_getset,
};

static PyObject * mark_carrier(PyObject * Py_UNUSED(module), PyObject * Py_UNUSED(ignored))
{
  carrier_thread = 1;
  atomic_store(&carriers_exist, 1);
  Py_RETURN_NONE;
}

/* poll(wait_set, timeout_ns) -> None: rcl_wait on rclpy's wait set (its
 * ``pointer``) keeping the GIL, where rclpy's own ``wait`` would let go of it
 * even for a poll: WaitSet_wait's poll, for the wait set rclpy fills. */
/* publisher_gid(publisher): the gid of the rcl publisher at that address, as
 * rclpy 9's message info gives a message's publisher_gid. */
static PyObject * publisher_gid(PyObject * Py_UNUSED(module), PyObject * arg)
{
  unsigned long long address = PyLong_AsUnsignedLongLong(arg);
  rmw_publisher_t * rmw_publisher;
  rmw_gid_t gid;
  if (address == (unsigned long long)-1 && PyErr_Occurred()) {
    return NULL;
  }
  rmw_publisher = rcl_publisher_get_rmw_handle((const rcl_publisher_t *)(uintptr_t)address);
  if (rmw_publisher == NULL) {
    return rcl_failed("rcl_publisher_get_rmw_handle");
  }
  if (rmw_get_gid_for_publisher(rmw_publisher, &gid) != RMW_RET_OK) {
    PyErr_Format(PyExc_RuntimeError, "rmw_get_gid_for_publisher failed: %s", rmw_get_error_string().str);
    rmw_reset_error();
    return NULL;
  }
  return gid_dict(&gid);
}

static PyObject * poll_wait_set(PyObject * Py_UNUSED(module), PyObject * const * args, Py_ssize_t nargs)
{
  rcl_wait_set_t * ws;
  long long timeout;
  rcl_ret_t ret;
  if (nargs != 2) {
    PyErr_SetString(PyExc_TypeError, "poll(wait_set, timeout_ns)");
    return NULL;
  }
  ws = (rcl_wait_set_t *)PyLong_AsVoidPtr(args[0]);
  if (ws == NULL) {
    if (!PyErr_Occurred()) {
      PyErr_SetString(PyExc_ValueError, "poll: no wait set at address 0");
    }
    return NULL;
  }
  timeout = PyLong_AsLongLong(args[1]);
  if (timeout == -1 && PyErr_Occurred()) {
    return NULL;
  }
  ret = rcl_wait(ws, (int64_t)poll_timeout(timeout));
  if (ret != RCL_RET_OK && ret != RCL_RET_TIMEOUT) {
    return rcl_failed("rcl_wait");
  }
  Py_RETURN_NONE;
}

static PyMethodDef module_methods[] = {
  {"poll", (PyCFunction)(void (*)(void))poll_wait_set, METH_FASTCALL,
   "poll(wait_set, timeout_ns) -> None: rcl_wait on rclpy's wait set at that address, keeping the GIL "
   "(for a wait whose guard condition is already triggered)"},
  {"publisher_gid", publisher_gid, METH_O,
   "publisher_gid(publisher) -> dict: the gid of the rcl publisher at that address, as rclpy 9's message "
   "info gives it ({'implementation_identifier': str, 'data': bytes})"},
  {"mark_carrier", mark_carrier, METH_NOARGS,
   "mark_carrier() -> None: this thread takes, after each plain callback, what it published to other "
   "plain callbacks (Notifier.carry); a notifier's waiter that wakes soon anyway is not woken for that"},
  {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
  PyModuleDef_HEAD_INIT,
  .m_name = "_fastpath",
  .m_doc = "The executor's hot path: readiness and takes of rcl entities (see the C source for why).",
  .m_size = -1,
  .m_methods = module_methods,
};

PyMODINIT_FUNC PyInit__fastpath(void)
{
  PyObject * m;
  if (PyType_Ready(&NotifierType) < 0 || PyType_Ready(&TakerType) < 0 || PyType_Ready(&WaitSetType) < 0 ||
      PyType_Ready(&LockType) < 0 || PyType_Ready(&ExpressType) < 0 || intern_names() < 0) {
    return NULL;
  }
  m = PyModule_Create(&module);
  if (m == NULL) {
    return NULL;
  }
  Py_INCREF(&NotifierType);
  Py_INCREF(&TakerType);
  Py_INCREF(&WaitSetType);
  Py_INCREF(&ExpressType);
  Py_INCREF(&LockType);
  if (PyModule_AddObject(m, "Notifier", (PyObject *)&NotifierType) < 0 ||
      PyModule_AddObject(m, "Lock", (PyObject *)&LockType) < 0 ||
      PyModule_AddObject(m, "Taker", (PyObject *)&TakerType) < 0 ||
      PyModule_AddObject(m, "WaitSet", (PyObject *)&WaitSetType) < 0 ||
      PyModule_AddObject(m, "Express", (PyObject *)&ExpressType) < 0 ||
      PyModule_AddIntConstant(m, "SUBSCRIPTION", KIND_SUBSCRIPTION) < 0 ||
      PyModule_AddIntConstant(m, "CLIENT", KIND_CLIENT) < 0 ||
      PyModule_AddIntConstant(m, "SERVICE", KIND_SERVICE) < 0 ||
      PyModule_AddIntConstant(m, "EVENT", KIND_EVENT) < 0 ||
      PyModule_AddIntConstant(m, "DRAIN", (long)DRAIN) < 0) {
    Py_DECREF(&NotifierType);
    Py_DECREF(&TakerType);
    Py_DECREF(&WaitSetType);
    Py_DECREF(&ExpressType);
    Py_DECREF(&LockType);
    Py_DECREF(m);
    return NULL;
  }
  return m;
}
