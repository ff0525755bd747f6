/* Taker: rcl_take of one subscription into a kept C message (see module.c). */
#include "fastpath.h"

/* A gid as rclpy 9 gives it in message info: {"implementation_identifier", "data"}. */
PyObject * gid_dict(const rmw_gid_t * gid)
{
  return Py_BuildValue(
    "{s:s,s:y#}", "implementation_identifier", gid->implementation_identifier, "data",
    (const char *)gid->data, (Py_ssize_t)RMW_GID_STORAGE_SIZE);
}

static int Taker_init(TakerObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {"subscription", "message_type", "publisher_gid", NULL};
  PyObject * subscription, * type;
  int with_gid = 0;
  if (!PyArg_ParseTupleAndKeywords(args, kwargs, "OO|$p", keywords, &subscription, &type, &with_gid)) {
    return -1;
  }
  if (self->message != NULL || self->subscription.handle != NULL) {
    PyErr_SetString(PyExc_RuntimeError, "Taker is initialised once");
    return -1;
  }
  self->with_gid = with_gid;
  if (message_functions(type, NULL, 0, &self->functions) < 0) {
    return -1;
  }
  if (held_enter(&self->subscription, subscription) < 0) {
    message_functions_clear(&self->functions);
    return -1;
  }
  self->message = self->functions.create();
  if (self->message == NULL) {
    held_exit(&self->subscription);
    message_functions_clear(&self->functions);
    PyErr_NoMemory();
    return -1;
  }
  return 0;
}

/* The kept message goes, and the handle with it. */
static void taker_close(TakerObject * self)
{
  if (self->message != NULL) {
    self->functions.destroy(self->message);
    self->message = NULL;
  }
  held_exit(&self->subscription);
}

static void Taker_dealloc(TakerObject * self)
{
  taker_close(self);
  message_functions_clear(&self->functions);
  Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyObject * Taker_close(TakerObject * self, PyObject * Py_UNUSED(ignored))
{
  taker_close(self);
  Py_RETURN_NONE;
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
PyObject * taker_take(TakerObject * self, int with_info)
{
  rmw_message_info_t info = rmw_get_zero_initialized_message_info();
  rcl_ret_t ret;
  PyObject * message;
  PyObject * dict;
  if (self->message == NULL) {
    PyErr_SetString(PyExc_RuntimeError, "Taker not initialised, or closed");
    return NULL;
  }
  ret = rcl_take(self->subscription.pointer, self->message, &info, NULL);
  if (ret == RCL_RET_SUBSCRIPTION_TAKE_FAILED) {
    Py_RETURN_NONE;
  }
  if (ret != RCL_RET_OK) {
    return rcl_failed("rcl_take");
  }
  message = self->functions.to_py(self->message);
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
  return taker_take(self, 0);
}

static PyObject * Taker_take_with_info(TakerObject * self, PyObject * Py_UNUSED(ignored))
{
  return taker_take(self, 1);
}

static PyMethodDef Taker_methods[] = {
  {"take", (PyCFunction)Taker_take, METH_NOARGS, "take() -> message | None"},
  {"take_with_info", (PyCFunction)Taker_take_with_info, METH_NOARGS,
   "take_with_info() -> (message, info) | None, info as rclpy's take_message gives it"},
  {"close", (PyCFunction)Taker_close, METH_NOARGS, "close() -> None: let the subscription's handle go"},
  {NULL, NULL, 0, NULL},
};

PyTypeObject TakerType = {
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

