/* Notifier: event-driven readiness for rcl subscriptions, clients and services (see module.c). */
#include "fastpath.h"

THREAD_LOCAL int carrier_thread = 0;
atomic_int carriers_exist = 0;

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

/* Wake the waiter whether it is armed or not (a guard triggered before its wait makes that wait return at
 * once): for a timer's reset (waitset.c), from any thread, with or without the GIL. */
void notifier_wake(NotifierObject * self)
{
  pthread_mutex_lock(&self->lock);
  if (self->guard != NULL) {
    trigger(self->guard);
  }
  pthread_mutex_unlock(&self->lock);
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
  PyObject * guard;
  if (!PyArg_ParseTupleAndKeywords(args, kwargs, "$O", keywords, &guard)) {
    return -1;
  }
  if (self->guard_held.handle != NULL) {
    PyErr_SetString(PyExc_RuntimeError, "Notifier is initialised once");
    return -1;
  }
  if (held_enter(&self->guard_held, guard) < 0) {
    return -1;
  }
  pthread_mutex_lock(&self->lock);
  self->guard = (rcl_guard_condition_t *)self->guard_held.pointer;
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
  self->guard_held.handle = NULL;
  self->guard_held.pointer = NULL;
  self->slots = NULL;
  self->ready = NULL;
  self->nready = self->capacity = 0;
  return (PyObject *)self;
}

/* rmw stops calling back for slot's entity (it serialises setting and
 * calling the callback: none runs once this returns), the slot leaves the
 * ready list, and its handle is let go. The caller unlinked it. */
static void forget_slot(NotifierObject * self, Slot * slot);

/* Stop triggering the guard, unwatch everything, let every handle go. */
static void notifier_close(NotifierObject * self)
{
  while (self->slots != NULL) {
    Slot * slot = self->slots;
    self->slots = slot->next;
    forget_slot(self, slot);
  }
  pthread_mutex_lock(&self->lock);
  self->guard = NULL;
  pthread_mutex_unlock(&self->lock);
  held_exit(&self->guard_held);
}

static void Notifier_dealloc(NotifierObject * self)
{
  notifier_close(self);
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
  PyObject * handle;
  int kind;
  int plain = 0;
  Slot * slot;
  rcl_ret_t ret;
  if (!PyArg_ParseTuple(args, "Oi|p", &handle, &kind, &plain)) {
    return NULL;
  }
  if (kind < KIND_SUBSCRIPTION || kind > KIND_EVENT) {
    PyErr_SetString(PyExc_ValueError, "watch() needs a known kind");
    return NULL;
  }
  if (self->guard_held.handle == NULL) {
    PyErr_SetString(PyExc_RuntimeError, "Notifier not initialised, or closed");
    return NULL;
  }
  slot = calloc(1, sizeof(Slot));
  if (slot == NULL) {
    return PyErr_NoMemory();
  }
  if (held_enter(&slot->entity, handle) < 0) {
    free(slot);
    return NULL;
  }
  if (find(self, (uintptr_t)slot->entity.pointer, NULL) != NULL) {
    held_exit(&slot->entity);
    free(slot);
    Py_RETURN_FALSE;
  }
  slot->owner = self;
  slot->key = (uintptr_t)slot->entity.pointer;
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
    held_exit(&slot->entity);
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

static void forget_slot(NotifierObject * self, Slot * slot)
{
  rcl_ret_t ret;
  size_t i;
  Py_BEGIN_ALLOW_THREADS
  ret = set_callback(slot->kind, slot->key, NULL, NULL);
  Py_END_ALLOW_THREADS
  if (ret != RCL_RET_OK) {
    rcl_reset_error();
  }
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
  held_exit(&slot->entity);
  free(slot);
}

static PyObject * Notifier_unwatch(NotifierObject * self, PyObject * handle)
{
  Slot ** link = &self->slots;
  Slot * slot;
  while ((slot = *link) != NULL && slot->entity.handle != handle) {
    link = &slot->next;
  }
  if (slot == NULL) {
    Py_RETURN_FALSE;
  }
  *link = slot->next;
  forget_slot(self, slot);
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

/* [(key, count), ...] of n reported pairs: built after the lock is let go. */
static PyObject * pairs(const uintptr_t * keys, const size_t * counts, Py_ssize_t n)
{
  PyObject * list = PyList_New(n);
  Py_ssize_t i;
  if (list == NULL) {
    return NULL;
  }
  for (i = 0; i < n; ++i) {
    PyObject * item = Py_BuildValue("(Kn)", (unsigned long long)keys[i], (Py_ssize_t)counts[i]);
    if (item == NULL) {
      Py_DECREF(list);
      return NULL;
    }
    PyList_SET_ITEM(list, i, item);
  }
  return list;
}

/* The keys of the entities that became ready since the last call, oldest
 * first; each appears once however many events it had. */
static PyObject * Notifier_ready(NotifierObject * self, PyObject * Py_UNUSED(ignored))
{
  uintptr_t inline_keys[REPORTED_INLINE];
  size_t inline_counts[REPORTED_INLINE];
  uintptr_t * keys = inline_keys;
  size_t * counts = inline_counts;
  PyObject * list;
  Py_ssize_t n;
  if (!atomic_load(&self->pending)) {
    return PyList_New(0);
  }
  n = notifier_take_reported(self, &keys, &counts, inline_keys, inline_counts);
  if (n < 0) {
    return NULL;
  }
  list = pairs(keys, counts, n);
  if (keys != inline_keys) {
    free(keys);
    free(counts);
  }
  /* What was taken out cannot go back: a failure here (out of memory) is
   * the caller's to report, and the wait set is rebuilt, which watches
   * again and so reports everything waiting. */
  return list;
}

/* Like ready(), for plain slots only; the others stay queued for ready().
 * A worker thread that just ran a plain callback takes what that callback's
 * publishes made ready for other plain callbacks, and runs the next one
 * itself instead of waking another thread. */
static PyObject * Notifier_carry(NotifierObject * self, PyObject * Py_UNUSED(ignored))
{
  uintptr_t inline_keys[REPORTED_INLINE];
  size_t inline_counts[REPORTED_INLINE];
  uintptr_t * keys = inline_keys;
  size_t * counts = inline_counts;
  PyObject * list;
  size_t i, n = 0, kept = 0, capacity = REPORTED_INLINE;
  if (!atomic_load(&self->plain_pending)) {
    return PyList_New(0);
  }
  pthread_mutex_lock(&self->lock);
  for (i = 0; i < self->nready; ++i) {
    Slot * slot = self->ready[i];
    if (!slot->plain) {
      self->ready[kept++] = slot;
      continue;
    }
    if (n == capacity) {
      size_t grown_capacity = capacity * 2;
      uintptr_t * grown_keys = malloc(grown_capacity * sizeof(uintptr_t));
      size_t * grown_counts = malloc(grown_capacity * sizeof(size_t));
      if (grown_keys == NULL || grown_counts == NULL) {
        /* Leave this and the rest queued for ready(). */
        free(grown_keys);
        free(grown_counts);
        for (; i < self->nready; ++i) {
          self->ready[kept++] = self->ready[i];
        }
        break;
      }
      memcpy(grown_keys, keys, n * sizeof(uintptr_t));
      memcpy(grown_counts, counts, n * sizeof(size_t));
      if (keys != inline_keys) {
        free(keys);
        free(counts);
      }
      keys = grown_keys;
      counts = grown_counts;
      capacity = grown_capacity;
    }
    keys[n] = slot->key;
    counts[n] = slot->count;
    ++n;
    slot->queued = 0;
    slot->count = 0;
    atomic_fetch_sub(&self->plain_pending, 1);
  }
  self->nready = kept;
  if (kept == 0) {
    atomic_store(&self->pending, 0);
  }
  pthread_mutex_unlock(&self->lock);
  list = pairs(keys, counts, (Py_ssize_t)n);
  if (keys != inline_keys) {
    free(keys);
    free(counts);
  }
  return list;
}

static PyObject * Notifier_close(NotifierObject * self, PyObject * Py_UNUSED(ignored))
{
  notifier_close(self);
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
   "watch(handle, kind, plain=False) -> bool: report new data of the rclpy handle's entity, held until "
   "unwatch (False: already watched)."},
  {"unwatch", (PyCFunction)Notifier_unwatch, METH_O,
   "unwatch(handle) -> bool: stop; no callback for it runs once this returns, then the handle is let go."},
  {"arm", (PyCFunction)Notifier_arm, METH_NOARGS,
   "arm() -> bool: about to wait; True if something is ready already (do not block)."},
  {"disarm", (PyCFunction)Notifier_disarm, METH_NOARGS, "disarm(): back from the wait."},
  {"pending", (PyCFunction)Notifier_pending, METH_NOARGS, "pending() -> bool: something is ready."},
  {"carry", (PyCFunction)Notifier_carry, METH_NOARGS,
   "carry() -> [(address, count)]: what ready() would give, of the plain slots only."},
  {"ready", (PyCFunction)Notifier_ready, METH_NOARGS,
   "ready() -> list[tuple[int, int]]: (entity, events) that became ready since the last call."},
  {"close", (PyCFunction)Notifier_close, METH_NOARGS,
   "close(): never trigger the guard again; unwatch everything and let every handle go."},
  {NULL, NULL, 0, NULL},
};

static PyGetSetDef Notifier_getset[] = {
  {"triggers", (getter)Notifier_get_triggers, NULL, "How often a callback woke the waiter.", NULL},
  {"watched", (getter)Notifier_get_watched, NULL, "How many entities are watched.", NULL},
  {NULL, NULL, NULL, NULL, NULL},
};

PyTypeObject NotifierType = {
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



/* What ready() gives, into C arrays (no Python objects): how many pairs were
 * moved into ``*keys`` and ``*counts`` (the given ``inline`` buffers of
 * REPORTED_INLINE, or malloc'd ones the caller frees when they differ), -1
 * out of memory (nothing consumed). */
Py_ssize_t notifier_take_reported(
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

